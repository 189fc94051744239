"""Does the action world model follow its actions? Retrieval over a controllability set (demos/controllability.py).

From each start's first frame the model rolls out `horizon` frames under each of the start's K recorded action
sequences. Rollout i should be nearer its own real future (sequence i replayed in the simulator) than any other
sequence's: the retrieval accuracy is the share of rollouts whose nearest real future is their own, by PSNR
averaged over the horizon, on the whole frame and on the object's region (the real future's object mask, dilated
as in image_fidelity.py).

Beside it, the same model with every action replaced by its null action: a model that ignores the actions makes
one rollout for all K sequences, so its retrieval is chance (1/K, ties shared) whatever the frames look like.
"""

import json
import logging
from collections import defaultdict
from dataclasses import asdict, dataclass, field
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import torch
from lerobot.configs.default import DatasetConfig

from lerobot_roboscape.dataset.reader import camera_names, episode_facts, episode_indices, open_dataset, read_episode
from lerobot_roboscape.dataset.segmentation import read_masks
from lerobot_roboscape.errors import InvalidInputError
from lerobot_roboscape.image_fidelity import OBJECT, OBJECT_DILATION, dilate, psnr
from lerobot_roboscape.tokenizer.modeling_tokenizer import VisualTokenizer
from lerobot_roboscape.training import resolve_device
from lerobot_roboscape.world_model.modeling_world_model import STWorldModel

logger = logging.getLogger(__name__)
REGIONS = ("whole_frame", "object")


@dataclass
class ControllabilityReportConfig:
    """Args:
    dataset: a controllability set (`roboscape-collect-control`): episodes with `start` and `sequence` facts.
    tokenizer: the world model's tokenizer.
    world_model: the action world model.
    output_dir: where controllability.json and controllability.png go.
    horizon: control steps compared per rollout (each sequence needs horizon + 1 frames); the model generates
        horizon // frame_skip frames, compared with the real frames they stand for.
    picture_starts: starts drawn in controllability.png (each sequence's real future beside its rollout).
    device: "auto", "cpu" or "cuda".
    """

    dataset: DatasetConfig = field(default_factory=lambda: DatasetConfig(repo_id="local/roboscape_controllability"))
    tokenizer: str = "outputs/tokenizer/pretrained_model"
    world_model: str = "outputs/world_model_action/pretrained_model"
    output_dir: Path = Path("outputs/controllability")
    horizon: int = 16
    picture_starts: int = 4
    device: str = "auto"


def retrieval_accuracy(similarity_KK: np.ndarray) -> float:
    """similarity[i, j]: rollout i against real future j. The share of rollouts whose most similar future is their
    own; a tie among the most similar counts as 1 / (tied futures) when their own is among them."""
    hits = []
    for i, row in enumerate(similarity_KK):
        best = np.isclose(row, row.max(), rtol=0, atol=1e-6)
        hits.append(best[i] / best.sum())
    return float(np.mean(hits))


def _groups(dataset) -> dict[int, list[int]]:
    """start -> its episodes ordered by sequence."""
    groups = defaultdict(dict)
    for index in episode_indices(dataset):
        facts = episode_facts(dataset, index)
        if "start" not in facts or "sequence" not in facts:
            raise InvalidInputError(
                f"{dataset.root} episode {index} has no start/sequence facts: not a controllability set "
                "(make one with roboscape-collect-control)"
            )
        groups[facts["start"]][facts["sequence"]] = index
    return {start: [seqs[k] for k in sorted(seqs)] for start, seqs in sorted(groups.items())}


@torch.no_grad()
def _similarities(pred, real, masks) -> dict[str, np.ndarray]:
    """pred: (K, T, n, 3, H, W) rollouts, real: (K, T, n, 3, H, W), masks: (K, T, n, H, W) labels -> per region
    (K, K) PSNR of rollout i against future j, averaged over steps and views (object: over the steps and views where
    future j shows the object)."""
    K, T, n = pred.shape[:3]
    out = {region: np.zeros((K, K)) for region in REGIONS}
    for j in range(K):
        region = dilate((masks[j] == OBJECT).flatten(0, 1), OBJECT_DILATION)  # (T * n, H, W)
        seen = region.flatten(1).sum(1) > 0
        for i in range(K):
            p, r = pred[i].flatten(0, 1), real[j].flatten(0, 1)
            out["whole_frame"][i, j] = psnr(p, r).mean().item()
            out["object"][i, j] = psnr(p[seen], r[seen], region[seen]).mean().item() if seen.any() else np.nan
    return out


def evaluate_controllability(cfg: ControllabilityReportConfig) -> dict:
    device = resolve_device(cfg.device)
    dataset = open_dataset(cfg.dataset.repo_id, cfg.dataset.root, cfg.dataset.episodes)
    tokenizer = VisualTokenizer.from_pretrained(cfg.tokenizer).to(device).eval()
    model = STWorldModel.from_pretrained(cfg.world_model).to(device).eval()
    if model.config.control != "action":
        raise InvalidInputError(f"{cfg.world_model} is a {model.config.control} world model, not an action one")
    cameras, n, k = camera_names(dataset), model.config.n_cameras, model.config.frame_skip
    T = max(1, cfg.horizon // k)  # model frames over the horizon's control steps
    future = k * np.arange(1, T + 1)  # the control steps those frames show
    per_start, pictures = [], []
    for start, indices in _groups(dataset).items():
        episodes = [read_episode(dataset, i) for i in indices]
        if min(len(e.action) for e in episodes) < T * k + 1:
            raise InvalidInputError(
                f"{dataset.root} start {start}: its sequences need {T * k + 1} frames for horizon {cfg.horizon}, the "
                f"shortest has {min(len(e.action) for e in episodes)}"
            )
        real = torch.stack(
            [torch.stack([torch.from_numpy(e.images[c][future]) for c in cameras], 1) for e in episodes]
        )  # (K, T, n, H, W, 3)
        real = real.permute(0, 1, 2, 5, 3, 4).to(device).float() / 255
        masks = torch.stack(
            [
                torch.from_numpy(np.stack(list(read_masks(dataset.root, i, cameras, len(e.action)).values()), 1))
                for i, e in zip(indices, episodes, strict=True)
            ]
        )[:, future].to(device)
        first = tokenizer.encode_views(
            [torch.from_numpy(episodes[0].images[c][:1]).permute(0, 3, 1, 2).to(device) for c in cameras]
        )  # (1, S): every sequence starts from this frame
        K = len(episodes)
        actions = torch.stack([torch.from_numpy(e.action[: T * k]) for e in episodes]).to(device)
        prompt = first[None].expand(K, -1, -1)
        rollouts = {
            "world_model": model.generate(prompt, T, actions=actions)[0],
            "ignoring_actions": model.generate(
                prompt, T, actions=torch.zeros_like(actions), no_action=torch.ones(K, T, dtype=torch.bool)
            )[0],
        }
        row = {"start": start, "episodes": indices, "task": episodes[0].task}
        for name, tokens in rollouts.items():
            pred = tokenizer.decode_views(tokens.flatten(0, 1), n).unflatten(0, (K, T))
            sims = _similarities(pred, real, masks)
            row[name] = {
                region: {"psnr": sims[region].tolist(), "retrieval": retrieval_accuracy(sims[region])}
                for region in REGIONS
                if not np.isnan(sims[region]).any()
            }
            if name == "world_model" and len(pictures) < cfg.picture_starts:
                pictures.append((real, pred))
        per_start.append(row)
        logger.info("start %d: retrieval %s", start, {r: v["retrieval"] for r, v in row["world_model"].items()})
    if not per_start:
        raise InvalidInputError(f"{dataset.root} has no start to measure")
    summary = {}
    for name in ("world_model", "ignoring_actions"):
        summary[name] = {}
        for region in REGIONS:
            measured = [r[name][region] for r in per_start if region in r[name]]
            if not measured:  # no start showed the object
                continue
            own, other = _own_and_other([m["psnr"] for m in measured])
            summary[name][region] = {
                "retrieval": float(np.mean([m["retrieval"] for m in measured])),
                "starts": len(measured),
                "own_future_psnr": float(np.mean(own)),
                "other_futures_psnr": float(np.mean(other)),
            }
    report = {
        "config": json.loads(json.dumps(asdict(cfg), default=str)),
        "sequences_per_start": len(per_start[0]["episodes"]),
        "horizon": cfg.horizon,
        "frame_skip": k,
        "summary": summary,
        "starts": per_start,
    }
    out = Path(cfg.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "controllability.json").write_text(json.dumps(report, indent=2))
    picture(pictures, out / "controllability.png")
    return report


def picture(starts: list[tuple[torch.Tensor, torch.Tensor]], path: Path, columns: int = 4) -> None:
    """Per start, a row per action sequence: its real future (left) and the rollout (right) at `columns` evenly
    spaced steps, first view. real/pred: (K, T, n, 3, H, W)."""
    blocks = []
    for real, pred in starts:
        steps = np.linspace(0, real.shape[1] - 1, columns).round().astype(int)
        rows = [
            torch.cat([torch.cat(list(real[k, steps, 0]), -1), torch.cat(list(pred[k, steps, 0]), -1)], -1)
            for k in range(real.shape[0])
        ]
        blocks.append(torch.cat(rows, -2))
    image = torch.cat(blocks, -2).clamp(0, 1).permute(1, 2, 0).cpu().numpy()
    iio.imwrite(path, (image * 255).round().astype(np.uint8))


def _own_and_other(matrices: list[list[list[float]]]) -> tuple[list[float], list[float]]:
    """The diagonal (rollout against its own future) and the rest of every (K, K) PSNR matrix."""
    own, other = [], []
    for m in map(np.asarray, matrices):
        diagonal = np.eye(len(m), dtype=bool)
        own += m[diagonal].tolist()
        other += m[~diagonal].tolist()
    return own, other
