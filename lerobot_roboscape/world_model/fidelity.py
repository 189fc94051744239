"""Fidelity report of the action world model: open-loop predictions against held-out episodes given the same actions.

For each episode the model reads `prompt_frames` real frames, then generates `horizon` frames from the recorded
actions alone. Per horizon step it reports PSNR, SSIM and LPIPS of the decoded prediction against the real frame,
next to the tokenizer's own reconstruction of the real frame (the best the world model could do). The done head
is scored against the recorded success labels, both teacher-forced (reading the real frames) and open-loop, and on
the failed episodes alone: how often it calls a failed attempt done (its false positives).
"""

import json
import logging
import warnings
from dataclasses import asdict, dataclass, field
from pathlib import Path

import av
import imageio.v3 as iio
import matplotlib
import numpy as np
import torch
from lerobot.configs.default import DatasetConfig
from torchmetrics.functional.classification import binary_auroc
from torchmetrics.functional.image import peak_signal_noise_ratio, structural_similarity_index_measure

from lerobot_roboscape.dataset.reader import camera_names, episode_indices, open_dataset, read_episode
from lerobot_roboscape.dataset.segmentation import has_masks, read_masks
from lerobot_roboscape.image_fidelity import frame_measures
from lerobot_roboscape.perceptual import load_lpips
from lerobot_roboscape.tokenizer.modeling_tokenizer import VisualTokenizer
from lerobot_roboscape.training import resolve_device
from lerobot_roboscape.world_model.modeling_world_model import STWorldModel

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from lerobot_roboscape.errors import InvalidInputError

logger = logging.getLogger(__name__)
METRICS = ("psnr", "ssim", "lpips")
# Of the task object (image_fidelity.py), when the held-out dataset has its masks: over views and the frames that
# show it.
OBJECT_METRICS = ("object_psnr", "object_survival")
LABELS = {
    "psnr": "PSNR",
    "ssim": "SSIM",
    "lpips": "LPIPS",
    "object_psnr": "object PSNR",
    "object_survival": "object survives",
}


@dataclass
class FidelityConfig:
    """Args:
    dataset: held-out episodes (--dataset.episodes; default: all episodes of the dataset).
    tokenizer: the tokenizer the world model was trained with (local directory or Hub repo id).
    world_model: the action world model (local directory or Hub repo id).
    output_dir: where fidelity.json, fidelity.md, fidelity.png and side_by_side.mp4 go.
    prompt_frames: real frames read before generating (default: the model's prompt_frames).
    horizon: generated frames compared per episode.
    max_episodes: episodes evaluated, at most.
    video_episodes: episodes shown in the side-by-side video.
    done_threshold: done probability counted as "done" for accuracy and false positives.
    lpips_weights: torchvision trunk weights for LPIPS (default: the torch hub cache).
    allow_random_lpips: report LPIPS from a random trunk when no weights are found (marked in the report).
    device: "auto", "cpu" or "cuda".
    """

    dataset: DatasetConfig = field(default_factory=lambda: DatasetConfig(repo_id="local/roboscape"))
    tokenizer: str = "outputs/tokenizer/pretrained_model"
    world_model: str = "outputs/world_model/pretrained_model"
    output_dir: Path = Path("outputs/fidelity")
    prompt_frames: int | None = None
    horizon: int = 16
    max_episodes: int = 8
    video_episodes: int = 2
    done_threshold: float = 0.5
    lpips_weights: Path | None = None
    allow_random_lpips: bool = False
    device: str = "auto"


def _image_metrics(pred, real, lpips_metric) -> dict[str, np.ndarray]:
    """Per frame, averaged over views: pred/real (T, n_cameras, 3, H, W) in [0, 1]."""
    p, r = pred.flatten(0, 1), real.flatten(0, 1)
    n = pred.shape[1]
    values = {
        "psnr": peak_signal_noise_ratio(p, r, data_range=1.0, reduction="none", dim=(1, 2, 3)),
        "ssim": structural_similarity_index_measure(p, r, data_range=1.0, reduction="none"),
        "lpips": lpips_metric(p * 2 - 1, r * 2 - 1).flatten(),
    }
    return {k: v.reshape(-1, n).mean(1).cpu().numpy() for k, v in values.items()}


def _object_metrics(pred, real, labels) -> dict[str, np.ndarray]:
    """Per frame, averaged over the views that show the object (NaN where none does): pred/real (T, n_cameras, 3,
    H, W) in [0, 1], labels (T, n_cameras, H, W)."""
    views = [frame_measures(pred[:, v], real[:, v], labels[:, v]) for v in range(pred.shape[1])]
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a frame where no view shows the object: NaN
        return {
            "object_psnr": np.nanmean([m["object_psnr"] for m in views], 0),
            "object_survival": np.nanmean([m["object_survives"] for m in views], 0),
        }


def _done_scores(prob: np.ndarray, label: np.ndarray, threshold: float) -> dict:
    positives = label > 0.5
    scores = {
        "accuracy": float(((prob >= threshold) == positives).mean()),
        "frames": int(len(label)),
        "positive_frames": int(positives.sum()),
    }
    if 0 < positives.sum() < len(label):
        scores["roc_auc"] = float(binary_auroc(torch.from_numpy(prob), torch.from_numpy(positives.astype(np.int64))))
    else:
        scores["roc_auc"] = None  # undefined with one class only
    return scores


def _false_positives(
    episodes: list[dict], tf_prob: list[np.ndarray], ol_prob: list[np.ndarray], threshold: float
) -> dict | None:
    """How often the done head calls a failed attempt (an episode never recorded done) done: over its frames,
    teacher-forced and open-loop, and per episode (`predicted_success`: its highest teacher-forced probability).
    None without a failed episode."""
    failed = [i for i, e in enumerate(episodes) if not e["recorded_success"]]
    if not failed:
        return None

    def rate(flagged: np.ndarray) -> dict:
        return {"rate": float(flagged.mean()), "flagged": int(flagged.sum()), "total": int(flagged.size)}

    return {
        "threshold": threshold,
        "failed_episodes": len(failed),
        "frames_teacher_forced": rate(np.concatenate([tf_prob[i] for i in failed]) >= threshold),
        "frames_open_loop": rate(np.concatenate([ol_prob[i] for i in failed]) >= threshold),
        "episodes": rate(np.array([episodes[i]["predicted_success"] for i in failed])),
    }


@torch.no_grad()
def _whole_episode_done(
    model: STWorldModel, episodes: list[tuple], rows: list[dict], prompt: int, batch_size: int = 16
) -> dict:
    """Success as the world model imagines it: each episode generated open loop from its prompt frames and its
    recorded actions to its end (as in a rollout of `roboscape_wm`); its score is the highest done probability.
    ROC-AUC of that score against the recorded success (None with one kind of episode only)."""
    scores = []
    for start in range(0, len(episodes), batch_size):
        chunk = episodes[start : start + batch_size]
        length = max(len(actions) for _, actions in chunk)  # frames; shorter episodes repeat their last action
        actions = torch.stack([torch.cat([a, a[-1:].expand(length - len(a), -1)]) for _, a in chunk])
        _, done = model.generate(torch.stack([p for p, _ in chunk]), length - prompt, actions=actions[:, : length - 1])
        scores += [float(d[: len(a) - prompt].max()) for d, (_, a) in zip(done, chunk, strict=True)]
    labels = np.array([row["recorded_success"] for row in rows])
    auc = None
    if 0 < labels.sum() < len(labels):
        auc = float(binary_auroc(torch.tensor(scores), torch.from_numpy(labels.astype(np.int64))))
    return {"roc_auc": auc, "episodes": len(scores), "successful": int(labels.sum()), "max_done": scores}


def _side_by_side(real, pred, prompt: int) -> np.ndarray:
    """(T, n_cameras, 3, H, W) real and predicted -> (T, n_cameras * H, 2 * W, 3) uint8: real left, predicted right.
    Prompt frames show the real frame on both sides."""
    both = torch.cat([real, torch.cat([real[:prompt], pred], 0)], dim=-1)  # (T, n, 3, H, 2W)
    video = both.permute(0, 1, 3, 4, 2).flatten(1, 2)  # (T, n * H, 2W, 3)
    return (video.clamp(0, 1) * 255).round().to(torch.uint8).cpu().numpy()


def evaluate_fidelity(cfg: FidelityConfig) -> dict:
    device = resolve_device(cfg.device)
    dataset = open_dataset(cfg.dataset.repo_id, cfg.dataset.root, cfg.dataset.episodes)
    tokenizer = VisualTokenizer.from_pretrained(cfg.tokenizer).to(device).eval()
    model = STWorldModel.from_pretrained(cfg.world_model).to(device).eval()
    if model.config.control != "action":
        raise InvalidInputError(
            f"{cfg.world_model} is a {model.config.control} world model; the fidelity report "
            "needs the action world model"
        )
    lpips_metric = load_lpips(tokenizer.config.lpips_net, cfg.lpips_weights, cfg.allow_random_lpips).to(device)
    prompt = cfg.prompt_frames or model.config.prompt_frames
    n_cameras = model.config.n_cameras

    masks = has_masks(dataset.root)
    metrics = METRICS + (OBJECT_METRICS if masks else ())
    per_step = {
        f"{kind}_{m}": [[] for _ in range(cfg.horizon)] for kind in ("prediction", "reconstruction") for m in metrics
    }
    tf_prob, tf_label, ol_prob, ol_label, episodes_out, videos, whole = [], [], [], [], [], [], []
    for index in episode_indices(dataset)[: cfg.max_episodes]:
        episode = read_episode(dataset, index)
        tokens = tokenizer.encode_views(
            [torch.from_numpy(f).permute(0, 3, 1, 2).to(device) for f in episode.images.values()]
        )  # (T, S)
        actions = torch.from_numpy(episode.action).to(device)
        horizon = min(cfg.horizon, len(tokens) - prompt)
        if horizon < 1:
            logger.warning(
                "episode %d has %d frames, not more than the %d prompt frames: skipped", index, len(tokens), prompt
            )
            continue
        pred_tokens, pred_done = model.generate(
            tokens[None, :prompt], horizon, actions=actions[None, : prompt + horizon - 1]
        )
        real = torch.stack([torch.from_numpy(f) for f in episode.images.values()], 1).permute(0, 1, 4, 2, 3)
        real = real.to(device).float() / 255  # (T, n, 3, H, W)
        target = real[prompt : prompt + horizon]
        pred = tokenizer.decode_views(pred_tokens[0], n_cameras)
        recon = tokenizer.decode_views(tokens[prompt : prompt + horizon], n_cameras)
        if masks:
            labels = read_masks(dataset.root, index, camera_names(dataset), len(tokens))
            labels = torch.from_numpy(np.stack(list(labels.values()), 1)[prompt : prompt + horizon]).to(device)
        for kind, images in (("prediction", pred), ("reconstruction", recon)):
            values = _image_metrics(images, target, lpips_metric)
            if masks:
                values |= _object_metrics(images, target, labels)
            for metric, per_frame in values.items():
                for step, value in enumerate(per_frame):
                    if not np.isnan(value):
                        per_step[f"{kind}_{metric}"][step].append(float(value))
        tf = model.teacher_forced(tokens[None], actions[None, :-1])[0][0].cpu().numpy()
        tf_prob.append(tf)
        tf_label.append(episode.done_label)
        ol_prob.append(pred_done[0].cpu().numpy())
        ol_label.append(episode.done_label[prompt : prompt + horizon])
        recorded = bool(episode.done_label.max() > 0.5)
        episodes_out.append(
            {
                "episode_index": index,
                "task": episode.task,
                "frames": len(tokens),
                "horizon": horizon,
                "recorded_success": recorded,
                "predicted_success": bool(tf.max() >= cfg.done_threshold),
            }
        )
        if len(videos) < cfg.video_episodes:
            videos.append(_side_by_side(real[: prompt + horizon], pred, prompt))
        whole.append((tokens[:prompt], actions))
    if not episodes_out:
        raise InvalidInputError(f"no episode of {dataset.root} is longer than the {prompt} prompt frames")

    report = {
        "config": json.loads(json.dumps(asdict(cfg), default=str)),
        "prompt_frames": prompt,
        "lpips_trunk": "random (not perceptual)" if lpips_metric.random_trunk else "pretrained",
        "per_step": {k: [float(np.mean(v)) if v else None for v in steps] for k, steps in per_step.items()},
        "mean": {k: float(np.mean(sum(steps, []))) if any(steps) else None for k, steps in per_step.items()},
        "done_teacher_forced": _done_scores(np.concatenate(tf_prob), np.concatenate(tf_label), cfg.done_threshold),
        "done_open_loop": _done_scores(np.concatenate(ol_prob), np.concatenate(ol_label), cfg.done_threshold),
        "episode_success_accuracy": float(
            np.mean([e["recorded_success"] == e["predicted_success"] for e in episodes_out])
        ),
        "done_false_positive": _false_positives(episodes_out, tf_prob, ol_prob, cfg.done_threshold),
        "done_whole_episode_open_loop": _whole_episode_done(model, whole, episodes_out, prompt),
        "episodes": episodes_out,
    }
    write_report(report, videos, Path(cfg.output_dir), fps=dataset.fps)
    return report


def write_report(report: dict, videos: list[np.ndarray], output_dir: Path, fps: int) -> None:
    output_dir.mkdir(parents=True, exist_ok=True)
    (output_dir / "fidelity.json").write_text(json.dumps(report, indent=2))
    (output_dir / "fidelity.md").write_text(markdown_table(report))
    plot(report, output_dir / "fidelity.png")
    if videos:
        av.logging.set_level(av.logging.ERROR)  # no encoder statistics on the console
        iio.imwrite(output_dir / "side_by_side.mp4", np.concatenate(videos), plugin="pyav", codec="libx264", fps=fps)


def markdown_table(report: dict) -> str:
    steps = len(report["per_step"]["prediction_psnr"])
    per_step = report["per_step"]
    metrics = [m for m in METRICS + OBJECT_METRICS if f"prediction_{m}" in per_step]
    names = [f"{LABELS[m]} {kind}" for m in metrics for kind in ("pred", "recon")]
    lines = [
        f"# World-model fidelity ({len(report['episodes'])} episodes, {report['prompt_frames']} prompt frames)",
        "",
        f"LPIPS trunk: {report['lpips_trunk']}. Reconstruction = the tokenizer's own round trip of the real frame."
        + (
            " Object columns: over the frames and views that show the task object."
            if len(metrics) > len(METRICS)
            else ""
        ),
        "",
        "| step | " + " | ".join(names) + " |",
        "|---:|" + "---:|" * len(names),
    ]
    fmt = lambda v: "-" if v is None else f"{v:.3f}"  # noqa: E731
    for i in range(steps):
        cells = [fmt(per_step[f"{kind}_{m}"][i]) for m in metrics for kind in ("prediction", "reconstruction")]
        lines.append(f"| {i + 1} | " + " | ".join(cells) + " |")
    for name in ("done_teacher_forced", "done_open_loop"):
        d = report[name]
        lines.append(
            f"\n{name}: accuracy {d['accuracy']:.3f}, ROC-AUC {fmt(d['roc_auc'])} "
            f"({d['positive_frames']}/{d['frames']} done frames)"
        )
    lines.append(f"\nepisode success predicted correctly: {report['episode_success_accuracy']:.3f}")
    whole = report["done_whole_episode_open_loop"]
    lines.append(
        f"\nwhole episodes generated open loop from their actions: ROC-AUC {fmt(whole['roc_auc'])} of the "
        f"highest done probability against success ({whole['successful']}/{whole['episodes']} successful)"
    )
    fp = report["done_false_positive"]
    if fp is None:
        lines.append("\ndone false positives: no failed episode among those evaluated")
    else:
        lines += [
            f"\ndone false positives on {fp['failed_episodes']} failed episodes (done probability >= "
            f"{fp['threshold']}):\n",
            "| counted over | rate | flagged / total |",
            "|---|---:|---:|",
        ]
        rows = {
            "frames, teacher-forced": "frames_teacher_forced",
            "frames, open-loop": "frames_open_loop",
            "episodes (highest teacher-forced)": "episodes",
        }
        for name, key in rows.items():
            lines.append(f"| {name} | {fp[key]['rate']:.3f} | {fp[key]['flagged']}/{fp[key]['total']} |")
    return "\n".join(lines) + "\n"


def plot(report: dict, path: Path) -> None:
    metrics = [m for m in METRICS + OBJECT_METRICS if f"prediction_{m}" in report["per_step"]]
    fig, axes = plt.subplots(1, len(metrics), figsize=(4 * len(metrics), 3.2))
    for ax, metric in zip(axes, metrics, strict=True):
        for kind, style in (("prediction", "-o"), ("reconstruction", "--")):
            values = [np.nan if v is None else v for v in report["per_step"][f"{kind}_{metric}"]]
            ax.plot(range(1, len(values) + 1), values, style, label=kind, markersize=3)
        ax.set_title(LABELS[metric])
        ax.set_xlabel("horizon step")
    axes[0].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
