"""Where `roboscape_wm`'s episodes start: frames of a LeRobot dataset's episodes (`dataset_starts`), the same saved
to a file that the env reads without the dataset (`export_starts`, `file_starts`), or frames given to `reset`
(another env's first observation), whose episode index is FROM_FRAMES."""

import json
from collections import Counter
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from lerobot_roboscape.dataset.reader import (
    action_range,
    camera_names,
    episode_facts,
    episode_indices,
    family_horizons,
    open_dataset,
    read_frames,
    read_states,
)
from lerobot_roboscape.envs.goal_bank import EpisodeStart
from lerobot_roboscape.io.tensor_files import load_tensors, save_tensors
from roboscape_core.errors import InvalidInputError

# The episode index of a start made from given frames (`reset(options={"frames": ...})`), not from the dataset.
FROM_FRAMES = -1


def checked_frames(frames: dict, cameras: list[str], shape: tuple[int, ...]) -> dict[str, np.ndarray]:
    """A batch of given frames (camera -> (B, H, W, 3) uint8) in the env's camera order, each of `shape`, checked."""
    if set(frames) != set(cameras):
        raise InvalidInputError(f"frames have cameras {sorted(frames)}, this env {cameras}")
    for cam, images in frames.items():
        if np.shape(images) != shape:
            raise InvalidInputError(f"frames[{cam!r}] has shape {np.shape(images)}, expected {shape}")
    return {cam: np.asarray(frames[cam], np.uint8) for cam in cameras}


def given_starts(cfg, tokens: torch.Tensor, tasks, horizons, states, state_dim: int | None) -> list[EpisodeStart]:
    """Starts of `roboscape_wm` (config `cfg`) from given frames, tokenized (B, S) (another env's first
    observation), with their instructions, horizons in control steps and the robot's states (B, D), which a world
    model with a state channel (`state_dim`) needs, e.g. the simulator's initial states for a paired evaluation.
    Their goals are the text model's from these frames, or goal frames that the reset gives (a real success of the
    same scene, say)."""
    if cfg.goal_source != "text_model":
        raise InvalidInputError(
            f"a start from given frames has no recorded last frame: goal_source must be text_model, not "
            f"{cfg.goal_source!r}"
        )
    B = len(tokens)
    if tasks is None or len(tasks) != B:
        raise InvalidInputError(f"frames need an instruction per episode ({B}), got {tasks!r}")
    horizons = np.broadcast_to(horizons, (B,))
    if state_dim is not None:
        if states is None or np.shape(states) != (B, state_dim):
            raise InvalidInputError(
                f"the action world model carries the robot's state: frames need options['states'] of shape "
                f"{(B, state_dim)} (observation.state of each start), got "
                f"{None if states is None else np.shape(states)}"
            )
        states = torch.as_tensor(np.asarray(states, np.float32))
    return [
        EpisodeStart(
            FROM_FRAMES,
            str(task),
            tokens[i],
            tokens[i],
            {},
            int(horizons[i]),
            first_state=None if states is None else states[i],
            last_state=None if states is None else states[i],
        )
        for i, task in enumerate(tasks)
    ]


def dataset_starts(
    cfg, repo_id: str, n_cameras: int, encode: Callable[[dict], torch.Tensor]
) -> tuple[list[EpisodeStart], list[str], tuple[np.ndarray, np.ndarray]]:
    """The starts of `roboscape_wm` (config `cfg`) from the episodes of its dataset that its families, split, scenes
    and starts_per_scene select, each at its branches' frames, tokenized by `encode` (camera -> frames to (k, S));
    the dataset's camera names and its per-dimension action range (low, high)."""
    dataset = open_dataset(repo_id, cfg.dataset_root)
    cameras = camera_names(dataset)
    if len(cameras) != n_cameras:
        raise InvalidInputError(
            f"dataset {dataset.root} has cameras {cameras} but the world model expects {n_cameras} views"
        )
    horizons = family_horizons(dataset) if cfg.episode_length is None else {}
    starts, per_scene = [], Counter()
    for index in episode_indices(dataset):
        facts = episode_facts(dataset, index)
        if cfg.families and facts.get("task_family") not in cfg.families:
            continue
        if cfg.split and facts.get("split") != cfg.split:
            continue
        if cfg.scenes and facts.get("scene") not in cfg.scenes:
            continue
        scene = (facts.get("task_family"), facts.get("scene"))
        if cfg.starts_per_scene is not None and per_scene[scene] >= cfg.starts_per_scene:
            continue
        per_scene[scene] += 1
        length = dataset.meta.episodes[index]["length"]
        branches = sorted({round(j * (length - 1) / cfg.branches_per_episode) for j in range(cfg.branches_per_episode)})
        tokens = encode(read_frames(dataset, index, [*branches, -1]))  # (branches + 1, S)
        states = torch.from_numpy(read_states(dataset, index, [*branches, -1]))
        task = dataset.meta.episodes[index]["tasks"][0]
        horizon = cfg.episode_length or horizons.get(facts.get("task_family"), horizons[None])
        starts += [
            EpisodeStart(
                index,
                task,
                tokens[j],
                tokens[-1],
                facts,
                horizon,
                frame,
                tokens[0] if frame else None,
                states[j],
                states[-1],
                states[0] if frame else None,
            )
            for j, frame in enumerate(branches)
        ]
    if not starts:
        raise InvalidInputError(
            f"no episode of {dataset.root} matches families={cfg.families} split={cfg.split!r} scenes={cfg.scenes}"
        )
    return starts, cameras, action_range(dataset)


# ---- a starts file: roboscape_wm without its dataset -------------------------------------------------------------

STARTS_FORMAT = 2  # 2: the robot's states beside the frames
# The config's fields that select and shape the starts: a file made with others would be the wrong starts.
SELECTION = ("families", "split", "scenes", "starts_per_scene", "branches_per_episode", "episode_length")


def export_starts(cfg, path: str | Path, device: str = "cpu") -> Path:
    """The starts of `roboscape_wm` (config `cfg`), read from its dataset and tokenized as the env does, saved to
    `path` (safetensors): an env given `starts_file=path` then runs without the dataset (or its videos), on a
    machine that has only the models."""
    from lerobot_roboscape.envs.loading import model_refs
    from lerobot_roboscape.tokenizer.modeling_tokenizer import VisualTokenizer

    tokenizer_ref, _, _, repo_id = model_refs(cfg)
    tokenizer = VisualTokenizer.from_pretrained(tokenizer_ref).to(device).eval()
    n_cameras = len(camera_names(open_dataset(repo_id, cfg.dataset_root)))

    starts, cameras, (low, high) = dataset_starts(
        cfg, repo_id, n_cameras, lambda frames: tokenizer.encode_frames(list(frames.values()))
    )
    tensors = {
        "first_tokens": torch.stack([s.first_tokens for s in starts]).cpu(),
        "last_tokens": torch.stack([s.last_tokens for s in starts]).cpu(),
        "episode_first_tokens": torch.stack([s.goal_prompt for s in starts]).cpu(),
        "first_states": torch.stack([s.first_state for s in starts]).cpu(),
        "last_states": torch.stack([s.last_state for s in starts]).cpu(),
        "episode_first_states": torch.stack([s.goal_prompt_state for s in starts]).cpu(),
    }
    rows = [
        {"episode_index": s.episode_index, "task": s.task, "facts": s.facts, "horizon": s.horizon, "frame": s.frame}
        for s in starts
    ]
    metadata = {
        "format": STARTS_FORMAT,
        "dataset": f"{repo_id} at {cfg.dataset_root}",
        "cameras": cameras,
        "action_range": [np.asarray(low).tolist(), np.asarray(high).tolist()],
        "selection": {name: getattr(cfg, name) for name in SELECTION},
        "starts": rows,
    }
    return save_tensors(path, tensors, {"starts": json.dumps(metadata)})


def file_starts(cfg, n_cameras: int) -> tuple[list[EpisodeStart], list[str], tuple[np.ndarray, np.ndarray], str]:
    """The starts saved by `export_starts` in cfg.starts_file, as `dataset_starts` returns them, and the dataset
    they were read from. The file must have been made with the config's selection of starts."""
    path = Path(cfg.starts_file)
    records, tensors = load_tensors(path, "export_starts", ("starts",))
    metadata = json.loads(records["starts"])
    if metadata.get("format") != STARTS_FORMAT:
        raise InvalidInputError(
            f"starts_file {path} has format {metadata.get('format')}, this version reads {STARTS_FORMAT}"
        )
    asked = json.loads(json.dumps({name: getattr(cfg, name) for name in SELECTION}))
    if differ := {k: (metadata["selection"][k], asked[k]) for k in SELECTION if metadata["selection"][k] != asked[k]}:
        raise InvalidInputError(f"starts_file {path} was made with other starts (file, config): {differ}")
    if len(metadata["cameras"]) != n_cameras:
        raise InvalidInputError(
            f"starts_file {path} has cameras {metadata['cameras']} but the world model expects {n_cameras} views"
        )
    starts = [
        EpisodeStart(
            row["episode_index"],
            row["task"],
            tensors["first_tokens"][i],
            tensors["last_tokens"][i],
            row["facts"],
            row["horizon"],
            row["frame"],
            tensors["episode_first_tokens"][i] if row["frame"] else None,
            tensors["first_states"][i],
            tensors["last_states"][i],
            tensors["episode_first_states"][i] if row["frame"] else None,
        )
        for i, row in enumerate(metadata["starts"])
    ]
    low, high = (np.asarray(bound, dtype=np.float32) for bound in metadata["action_range"])
    return starts, metadata["cameras"], (low, high), metadata["dataset"]
