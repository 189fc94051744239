"""Does the action world model follow its actions? Retrieval over a controllability set (demos/controllability.py).

From each start's first frame the model rolls out `horizon` frames under each of the start's K recorded action
sequences. Rollout i should be nearer its own real future (sequence i replayed in the simulator) than any other
sequence's: the retrieval accuracy is the share of rollouts whose nearest real future is their own, by PSNR
averaged over the horizon, on the whole frame and on the object's region (the real future's object mask, dilated
as in metrics/image_fidelity.py).

Beside it, the same model with every action replaced by its null action: a model that ignores the actions makes
one rollout for all K sequences, so its retrieval is chance (1/K, ties shared) whatever the frames look like.

The likelihood retrieval reads the same question from the model's likelihood instead of its rollouts: each real
future, frame by frame after its real past and fully masked as a rollout's first decoding step sees it, is scored
under each of the K sequences; it is retrieved when its own sequence explains it best. A model that knows what the
actions do but whose decoding hides it scores here and not in the rollouts; a model that ignores them scores chance.

The action gain is Genie's delta-PSNR: the PSNR of each rollout to its real future, minus the PSNR to that future
of the rollout from the same start under another start's actions (the next start's sequence of the same index).

Beside them, the measures that see the arm (`arm_measures.py`): the TCP's error and retrieval by state, the arm
region's PSNR and the motion ratio.
"""

import json
import logging
from collections import defaultdict
from dataclasses import asdict, dataclass, field
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import torch
import torch.nn.functional as F
from lerobot.configs.default import DatasetConfig

from lerobot_roboscape.dataset.reader import camera_names, episode_facts, episode_indices, open_dataset, read_episode
from lerobot_roboscape.dataset.segmentation import read_masks
from lerobot_roboscape.io.tensor_files import load_tensors, save_tensors
from lerobot_roboscape.metrics.image_fidelity import OBJECT, OBJECT_DILATION, dilate, psnr
from lerobot_roboscape.tokenizer.modeling_tokenizer import VisualTokenizer
from lerobot_roboscape.training.loop import resolve_device
from lerobot_roboscape.world_model.measures.arm_measures import arm_measures, summarise_arm
from lerobot_roboscape.world_model.measures.retrieval import retrieval_accuracy
from lerobot_roboscape.world_model.modeling_world_model import STWorldModel
from roboscape_core.errors import InvalidInputError

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


@dataclass
class ControlStart:
    """One start of a controllability set, read for a model's frame skip k over a horizon of T model frames."""

    start: int
    episodes: list[int]
    task: str
    first: torch.Tensor  # (1, S) tokens of the frame every sequence starts from
    actions: torch.Tensor  # (K, T * k, A) each sequence's actions
    real: torch.Tensor  # (K, T, n, 3, H, W) uint8: the frames at control steps k, 2k, .., T * k
    masks: torch.Tensor  # (K, T, n, H, W) labels of those frames
    first_state: torch.Tensor  # (1, D) the robot's state in the first frame
    states: torch.Tensor  # (K, T, D) its states in the real frames at control steps k, 2k, .., T * k


def read_control_set(dataset, tokenizer: VisualTokenizer, frame_skip: int, horizon: int, device) -> list[ControlStart]:
    """Every start of a controllability set, its real futures at the model frames of `horizon` control steps."""
    cameras, k = camera_names(dataset), frame_skip
    T = max(1, horizon // k)  # model frames over the horizon's control steps
    future = k * np.arange(1, T + 1)  # the control steps those frames show
    starts = []
    for start, indices in _groups(dataset).items():
        episodes = [read_episode(dataset, i) for i in indices]
        if min(len(e.action) for e in episodes) < T * k + 1:
            raise InvalidInputError(
                f"{dataset.root} start {start}: its sequences need {T * k + 1} frames for horizon {horizon}, the "
                f"shortest has {min(len(e.action) for e in episodes)}"
            )
        real = torch.stack([torch.stack([torch.from_numpy(e.images[c][future]) for c in cameras], 1) for e in episodes])
        masks = [
            np.stack(list(read_masks(dataset.root, i, cameras, len(e.action)).values()), 1)
            for i, e in zip(indices, episodes, strict=True)
        ]
        first = tokenizer.encode_frames([episodes[0].images[c][:1] for c in cameras])
        starts.append(
            ControlStart(
                start,
                indices,
                episodes[0].task,
                first,
                torch.stack([torch.from_numpy(e.action[: T * k]) for e in episodes]).to(device),
                real.permute(0, 1, 2, 5, 3, 4).to(device),  # (K, T, n, 3, H, W)
                torch.from_numpy(np.stack(masks))[:, future].to(device),
                torch.from_numpy(episodes[0].state[:1]).to(device),
                torch.stack([torch.from_numpy(e.state[future]) for e in episodes]).to(device),
            )
        )
    if not starts:
        raise InvalidInputError(f"{dataset.root} has no start to measure")
    return starts


def spread(starts: list[ControlStart], keep: int) -> list[ControlStart]:
    """At most `keep` of the starts, evenly spread over the set (over its scenes, as collected)."""
    picked = np.linspace(0, len(starts) - 1, min(keep, len(starts))).round().astype(int)
    return [starts[i] for i in np.unique(picked)]


CONTROL_STARTS_FIELDS = ("first", "actions", "real", "masks", "first_state", "states")


def save_control_starts(starts: list[ControlStart], path: str | Path, frame_skip: int) -> None:
    """A controllability set as read for a model's frame skip, in one safetensors file (tensors, and the starts'
    facts in its metadata): what a machine without the datasets' videos measures retrieval on."""
    tensors = {
        f"{i}.{name}": getattr(s, name).cpu().contiguous()
        for i, s in enumerate(starts)
        for name in CONTROL_STARTS_FIELDS
    }
    facts = [{"start": s.start, "episodes": s.episodes, "task": s.task} for s in starts]
    save_tensors(path, tensors, {"starts": json.dumps(facts), "frame_skip": str(frame_skip)})


def load_control_starts(path: str | Path, frame_skip: int, device="cpu") -> list[ControlStart]:
    """The starts `save_control_starts` wrote; refuses a file read for another frame skip."""
    metadata, tensors = load_tensors(path, "save_control_starts", ("starts", "frame_skip"), device)
    if "0.states" not in tensors:
        raise InvalidInputError(
            f"{path} was saved before controllability sets carried the robot's states; read its set again "
            "(save_control_starts)"
        )
    if int(metadata["frame_skip"]) != frame_skip:
        raise InvalidInputError(
            f"{path} was read for frame_skip={metadata['frame_skip']}, the model steps every {frame_skip} control steps"
        )
    return [
        ControlStart(
            facts["start"], facts["episodes"], facts["task"], *(tensors[f"{i}.{n}"] for n in CONTROL_STARTS_FIELDS)
        )
        for i, facts in enumerate(json.loads(metadata["starts"]))
    ]


@torch.no_grad()
def measure_start(
    model, tokenizer: VisualTokenizer, start: ControlStart, other: ControlStart, null: bool, temperature: float = 0.0
) -> dict:
    """Rollouts of one start under its K sequences (and, for the action gain, under `other` start's sequences;
    with `null`, under the null action), in one batch, decoded at `temperature` (0: MaskGIT's argmax). Returns for
    "world_model" (and "ignoring_actions") the (K, K) PSNR per region and the decoded rollouts, the action gain (dB,
    mean over the K sequences) and the measures that see the arm (`arm_measures`)."""
    K, T = start.real.shape[:2]
    kinds = {"world_model": start.actions, "other_actions": other.actions[:K]}
    if null:
        kinds["ignoring_actions"] = torch.zeros_like(start.actions)
    actions = torch.cat(list(kinds.values()))
    no_action = torch.zeros(len(actions), T, dtype=torch.bool, device=actions.device)
    if null:
        no_action[-K:] = True
    prompt = start.first[None].expand(len(actions), -1, -1)
    states = start.first_state[None].expand(len(actions), -1, -1) if model.config.state else None
    generated = model.generate(prompt, T, actions=actions, no_action=no_action, states=states, temperature=temperature)
    pred = tokenizer.decode_views(generated.tokens.flatten(0, 1), model.config.n_cameras)
    pred = pred.unflatten(0, (len(actions), T))
    real = start.real.float() / 255
    out = {}
    for i, name in enumerate(kinds):
        rollouts = pred[i * K : (i + 1) * K]
        if name != "other_actions":  # that one is only read against its own sequence's future, below
            out[name] = {"similarity": _similarities(rollouts, real, start.masks), "pred": rollouts}
    own = out["world_model"]["similarity"]["whole_frame"].diagonal()
    other_psnr = np.array([psnr(pred[K + j], real[j]).mean().item() for j in range(K)])
    out["action_gain"] = float(np.mean(own - other_psnr))
    predicted_states = None if generated.state is None else generated.state[:K]
    out["arm"] = arm_measures(tokenizer, start, out["world_model"]["pred"], predicted_states, model.config.window)
    return out


@torch.no_grad()
def likelihood_retrieval(model, tokenizer: VisualTokenizer, start: ControlStart) -> float:
    """Share of the start's K real futures that their own action sequence explains best: the mean cross-entropy of
    the future's tokens, each frame predicted fully masked from the real frames before it (at most a window)."""
    K, T = start.real.shape[:2]
    n, window = model.config.n_cameras, model.config.window
    real = torch.stack([tokenizer.encode_views([start.real[j, :, c] for c in range(n)]) for j in range(K)])
    futures = torch.cat([start.first[None].expand(K, -1, -1), real], 1)  # (K, T + 1, S)
    index = torch.arange(K, device=futures.device)
    control = model.episode_control(start.actions[index.repeat_interleave(K)])
    tokens = futures[index.repeat(K)]  # (K * K, T + 1, S): pair (actions i, future j) at i * K + j
    states = None
    if model.config.state:  # each future's real states, as teacher forcing reads them
        states = torch.cat([start.first_state[None].expand(K, -1, -1), start.states], 1)[index.repeat(K)]
    nll = torch.zeros(K * K, device=tokens.device)
    for t in range(1, T + 1):
        seen = slice(max(0, t + 1 - window), t + 1)
        inputs = tokens[:, seen].clone()
        inputs[:, -1] = model.config.mask_token_id
        seen_states = None if states is None else states[:, seen]
        logits = model.compute_logits(inputs, control.frames(seen), states=seen_states, anchor=tokens[:, 0])[0]
        logits = logits[:, -1]  # (K * K, S, V)
        nll += F.cross_entropy(logits.transpose(1, 2).float(), tokens[:, t], reduction="none").mean(1)
    return retrieval_accuracy(-nll.view(K, K).T.cpu().numpy())  # row j: future j under each sequence


def control_summary(
    model, tokenizer: VisualTokenizer, starts: list[ControlStart], temperature: float = 0.0
) -> dict[str, float]:
    """Retrieval (whole frame, object) and action gain over a controllability set: the held-out measures that
    size the action model's training (rollouts decoded at `temperature`)."""
    retrieval, gain, likelihood, arm = defaultdict(list), [], [], []
    for i, start in enumerate(starts):
        other = starts[(i + 1) % len(starts)]
        measured = measure_start(model, tokenizer, start, other, null=False, temperature=temperature)
        for region, sims in measured["world_model"]["similarity"].items():
            if not np.isnan(sims).any():
                retrieval[region].append(retrieval_accuracy(sims))
        gain.append(measured["action_gain"])
        likelihood.append(likelihood_retrieval(model, tokenizer, start))
        arm.append(measured["arm"])
    return {
        **{f"retrieval_{region}": float(np.mean(v)) for region, v in retrieval.items()},
        "action_gain_db": float(np.mean(gain)),
        "likelihood_retrieval": float(np.mean(likelihood)),
        **summarise_arm(arm),
    }


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
    k = model.config.frame_skip
    starts = read_control_set(dataset, tokenizer, k, cfg.horizon, device)
    per_start, pictures, gains = [], [], []
    for i, start in enumerate(starts):
        measured = measure_start(model, tokenizer, start, starts[(i + 1) % len(starts)], null=True)
        row = {
            "start": start.start,
            "episodes": start.episodes,
            "task": start.task,
            "action_gain": measured["action_gain"],
            "likelihood_retrieval": likelihood_retrieval(model, tokenizer, start),
            "arm": measured["arm"],
        }
        gains.append(measured["action_gain"])
        for name in ("world_model", "ignoring_actions"):
            sims = measured[name]["similarity"]
            row[name] = {
                region: {"psnr": sims[region].tolist(), "retrieval": retrieval_accuracy(sims[region])}
                for region in REGIONS
                if not np.isnan(sims[region]).any()
            }
        if len(pictures) < cfg.picture_starts:
            pictures.append((start.real.float() / 255, measured["world_model"]["pred"]))
        per_start.append(row)
        logger.info("start %d: retrieval %s", start.start, {r: v["retrieval"] for r, v in row["world_model"].items()})
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
    summary["action_gain_db"] = float(np.mean(gains))
    summary["likelihood_retrieval"] = float(np.mean([r["likelihood_retrieval"] for r in per_start]))
    summary["arm"] = summarise_arm([r["arm"] for r in per_start])
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
