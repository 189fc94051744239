"""Fidelity report of the action world model: open-loop predictions against held-out episodes given the same actions.

For each episode the model reads `prompt_frames` real model frames, then generates `horizon` control steps (a frame
per `frame_skip` steps) from the recorded actions alone. Per generated frame it reports PSNR, SSIM and LPIPS of the
decoded prediction against the real frame, next to the tokenizer's own reconstruction of the real frame (the best
the world model could do), on the whole frame, on the task object's region and on the arm's (the robot's mask, dilated
as the object's); and the motion ratio, the prediction's mean change from frame to frame over the real frames' (a
model that stops moving keeps a good PSNR and a ratio near 0). The done signals have their own
report (reward/done_report.py), and so does whether the model follows its actions (`controllability.py`).
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
from torchmetrics.functional.image import peak_signal_noise_ratio, structural_similarity_index_measure

from lerobot_roboscape.dataset.reader import camera_names, episode_indices, open_dataset, read_episode
from lerobot_roboscape.dataset.segmentation import ROBOT, has_masks, read_masks
from lerobot_roboscape.io.templates import render_report
from lerobot_roboscape.metrics.image_fidelity import OBJECT_DILATION, dilate, frame_measures, psnr
from lerobot_roboscape.metrics.perceptual import load_lpips
from lerobot_roboscape.tokenizer.modeling_tokenizer import VisualTokenizer
from lerobot_roboscape.training.loop import resolve_device
from lerobot_roboscape.world_model.clips import model_frames
from lerobot_roboscape.world_model.measures.controllability import ControllabilityReportConfig, evaluate_controllability
from lerobot_roboscape.world_model.modeling_world_model import STWorldModel

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from roboscape_core.errors import InvalidInputError

REPORT_JSON = "fidelity.json"


def read_fidelity(folder: Path) -> dict | None:
    """The report `evaluate_fidelity` wrote into `folder` (None where none was made)."""
    path = Path(folder) / REPORT_JSON
    return json.loads(path.read_text()) if path.is_file() else None


def results_entry(report: dict) -> dict:
    """What a run's results.json keeps of a fidelity report: the means, the per-step measures and the
    controllability readings."""
    return {k: report[k] for k in ("mean", "per_step", "controllability", "controllability_long") if k in report}


logger = logging.getLogger(__name__)
METRICS = ("psnr", "ssim", "lpips")
# Of the task object (metrics/image_fidelity.py), when the held-out dataset has its masks: over views and the
# frames that show it.
OBJECT_METRICS = ("object_psnr", "object_survival", "arm_psnr")
LABELS = {
    "psnr": "PSNR",
    "ssim": "SSIM",
    "lpips": "LPIPS",
    "object_psnr": "object PSNR",
    "object_survival": "object survives",
    "arm_psnr": "arm PSNR",
}


@dataclass
class FidelityConfig:
    """Args:
    dataset: held-out episodes (--dataset.episodes; default: all episodes of the dataset).
    tokenizer: the tokenizer the world model was trained with (local directory or Hub repo id).
    world_model: the action world model (local directory or Hub repo id).
    output_dir: where fidelity.json, fidelity.md, fidelity.png and side_by_side.mp4 go.
    prompt_frames: real frames read before generating (default: the model's prompt_frames).
    horizon: control steps generated per episode (horizon // frame_skip model frames are compared).
    max_episodes: episodes evaluated, at most.
    video_episodes: episodes shown in the side-by-side video.
    controllability: a controllability set (`roboscape-collect-control`); when given, the report also says whether
        the model follows its actions (world_model/measures/controllability.py, controllability.json).
    long_horizon: control steps of a second, longer controllability reading (output_dir/long_horizon); null: none.
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
    controllability: DatasetConfig | None = None
    long_horizon: int | None = 48
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
    """Per frame, averaged over the views that show the object (the arm's: those that show the arm; NaN where none
    does): pred/real (T, n_cameras, 3, H, W) in [0, 1], labels (T, n_cameras, H, W)."""
    views = [frame_measures(pred[:, v], real[:, v], labels[:, v]) for v in range(pred.shape[1])]
    arm = dilate((labels == ROBOT).flatten(0, 1), OBJECT_DILATION)
    seen = arm.flatten(1).any(1)
    arm_psnr = torch.full(seen.shape, float("nan"), device=pred.device)
    if seen.any():
        arm_psnr[seen] = psnr(pred.flatten(0, 1)[seen].float(), real.flatten(0, 1)[seen].float(), arm[seen])
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a frame where no view shows the object: NaN
        return {
            "object_psnr": np.nanmean([m["object_psnr"] for m in views], 0),
            "object_survival": np.nanmean([m["object_survives"] for m in views], 0),
            "arm_psnr": np.nanmean(arm_psnr.view(labels.shape[:2]).cpu().numpy(), 1),
        }


def motion(frames) -> float:
    """Mean absolute change from frame to frame of (T, n, 3, H, W) images."""
    return float((frames[1:] - frames[:-1]).abs().mean())


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
    n_cameras, k = model.config.n_cameras, model.config.frame_skip
    horizon_frames = max(1, cfg.horizon // k)  # the horizon is in control steps; the model makes a frame per k

    masks = has_masks(dataset.root)
    metrics = METRICS + (OBJECT_METRICS if masks else ())
    per_step = {
        f"{kind}_{m}": [[] for _ in range(horizon_frames)] for kind in ("prediction", "reconstruction") for m in metrics
    }
    episodes_out, videos = [], []
    for index in episode_indices(dataset)[: cfg.max_episodes]:
        episode = read_episode(dataset, index)
        frames = model_frames(len(episode.action), k)
        images = {camera: f[frames] for camera, f in episode.images.items()}
        tokens = tokenizer.encode_frames(list(images.values()))  # (T, S), T model frames
        actions = torch.from_numpy(episode.action).to(device)
        horizon = min(horizon_frames, len(tokens) - prompt)
        if horizon < 1:
            logger.warning(
                "episode %d has %d frames, not more than the %d prompt frames: skipped", index, len(tokens), prompt
            )
            continue
        states = torch.from_numpy(episode.state[frames][None, :prompt]).to(device)
        pred_tokens = model.generate(
            tokens[None, :prompt], horizon, actions=actions[None, : (prompt + horizon - 1) * k], states=states
        ).tokens
        real = torch.stack([torch.from_numpy(f) for f in images.values()], 1).permute(0, 1, 4, 2, 3)
        real = real.to(device).float() / 255  # (T, n, 3, H, W)
        target = real[prompt : prompt + horizon]
        pred = tokenizer.decode_views(pred_tokens[0], n_cameras)
        recon = tokenizer.decode_views(tokens[prompt : prompt + horizon], n_cameras)
        labels = None
        if masks:
            labels = read_masks(dataset.root, index, camera_names(dataset), len(episode.action))
            labels = np.stack(list(labels.values()), 1)[frames]
            labels = torch.from_numpy(labels[prompt : prompt + horizon]).to(device)
        _measure({"prediction": pred, "reconstruction": recon}, target, lpips_metric, labels, per_step)
        # both from the tokenizer's picture of the last prompt frame: its own error is not motion
        last = tokenizer.decode_views(tokens[prompt - 1 : prompt], n_cameras)
        ratio = motion(torch.cat([last, pred])) / max(motion(torch.cat([last, recon])), 1e-6)
        episodes_out.append(
            {
                "episode_index": index,
                "task": episode.task,
                "frames": len(tokens),
                "horizon": horizon,
                "frame_skip": k,
                "motion_ratio": ratio,
            }
        )
        if len(videos) < cfg.video_episodes:
            videos.append(_side_by_side(real[: prompt + horizon], pred, prompt))
    if not episodes_out:
        raise InvalidInputError(f"no episode of {dataset.root} is longer than the {prompt} prompt frames")

    report = {
        "config": json.loads(json.dumps(asdict(cfg), default=str)),
        "prompt_frames": prompt,
        "lpips_trunk": "random (not perceptual)" if lpips_metric.random_trunk else "pretrained",
        "per_step": {k: [float(np.mean(v)) if v else None for v in steps] for k, steps in per_step.items()},
        "mean": {k: float(np.mean(sum(steps, []))) if any(steps) else None for k, steps in per_step.items()},
        "episodes": episodes_out,
        "motion_ratio": float(np.mean([e["motion_ratio"] for e in episodes_out])),
    }
    if cfg.controllability is not None:
        report |= _controllability(cfg)
    write_report(report, videos, Path(cfg.output_dir), fps=dataset.fps)
    return report


def _measure(decoded: dict, target, lpips_metric, labels, per_step: dict) -> None:
    """Each decoding's ({kind: frames}) image measures against the real frames, and the object's where the frames
    have masks (`labels`), added to `per_step` ({kind_measure: [values of each step]}); NaN (no object) is left out."""
    for kind, images in decoded.items():
        values = _image_metrics(images, target, lpips_metric)
        if labels is not None:
            values |= _object_metrics(images, target, labels)
        for metric, per_frame in values.items():
            for step, value in enumerate(per_frame):
                if not np.isnan(value):
                    per_step[f"{kind}_{metric}"][step].append(float(value))


def _controllability(cfg: FidelityConfig) -> dict:
    """The controllability report's summary at the fidelity horizon (and at `long_horizon` where asked)."""
    readings = {"controllability": (cfg.horizon, cfg.output_dir)}
    if cfg.long_horizon:
        readings["controllability_long"] = (cfg.long_horizon, Path(cfg.output_dir) / "long_horizon")
    return {
        name: evaluate_controllability(
            ControllabilityReportConfig(
                cfg.controllability, cfg.tokenizer, cfg.world_model, folder, horizon, device=cfg.device
            )
        )["summary"]
        for name, (horizon, folder) in readings.items()
    }


def write_report(report: dict, videos: list[np.ndarray], output_dir: Path, fps: int) -> None:
    output_dir.mkdir(parents=True, exist_ok=True)
    (output_dir / REPORT_JSON).write_text(json.dumps(report, indent=2))
    (output_dir / "fidelity.md").write_text(markdown(report))
    plot(report, output_dir / "fidelity.png")
    if videos:
        av.logging.set_level(av.logging.ERROR)  # no encoder statistics on the console
        iio.imwrite(output_dir / "side_by_side.mp4", np.concatenate(videos), plugin="pyav", codec="libx264", fps=fps)


def headline(report: dict) -> str:
    """The report in one line, for a run's console: the open loop's mean against the tokenizer's own, and the
    retrieval of each region."""
    mean = report["mean"]
    return (
        f"PSNR {mean['prediction_psnr']:.1f} dB (tokenizer alone {mean['reconstruction_psnr']:.1f}), "
        f"SSIM {mean['prediction_ssim']:.2f}"
        + "".join(
            f", retrieval {region} {m['retrieval']:.2f}"
            for region, m in report.get("controllability", {}).get("world_model", {}).items()
        )
    )


def _measured(report: dict) -> list[str]:
    """The metrics the report holds: the object ones only where the data had masks."""
    return [m for m in METRICS + OBJECT_METRICS if f"prediction_{m}" in report["per_step"]]


def markdown(report: dict) -> str:
    metrics = _measured(report)
    return render_report(
        "fidelity_report.md", report=report, metrics=metrics, labels=LABELS, object_columns=len(metrics) > len(METRICS)
    )


def plot(report: dict, path: Path) -> None:
    metrics = _measured(report)
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
