"""Where `roboscape_wm`'s episodes start: frames of a LeRobot dataset's episodes (`dataset_starts`), or frames given
to `reset` (another env's first observation), whose episode index is FROM_FRAMES."""

from collections import Counter
from collections.abc import Callable

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
)
from lerobot_roboscape.envs.goal_bank import EpisodeStart
from roboscape_core.errors import InvalidInputError

# The episode index of a start made from given frames (`reset(options={"frames": ...})`), not from the dataset.
FROM_FRAMES = -1


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
        task = dataset.meta.episodes[index]["tasks"][0]
        horizon = cfg.episode_length or horizons.get(facts.get("task_family"), horizons[None])
        starts += [
            EpisodeStart(index, task, tokens[j], tokens[-1], facts, horizon, frame, tokens[0] if frame else None)
            for j, frame in enumerate(branches)
        ]
    if not starts:
        raise InvalidInputError(
            f"no episode of {dataset.root} matches families={cfg.families} split={cfg.split!r} scenes={cfg.scenes}"
        )
    return starts, cameras, action_range(dataset)
