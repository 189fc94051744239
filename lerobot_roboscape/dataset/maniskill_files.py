"""Reads official ManiSkill trajectory files (`.h5` + `.json`, written by RecordEpisode, the motion-planning
runner or `replay_trajectory`) as `Episode`s, whatever the control mode and cameras."""

import json
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from lerobot_roboscape.dataset.episode import Episode
from roboscape_core.errors import InvalidInputError, MissingInputError

RENDER_HINT = (
    "It has no camera images. Render them by replaying it first, e.g.\n"
    "  python -m mani_skill.trajectory.replay_trajectory --traj-path {h5} --obs-mode rgb --save-traj "
    "--use-env-states --allow-failure\nthen convert the new file it writes (same folder, '.rgb.' in its name)."
)


@dataclass
class TrajectoryFile:
    h5_path: Path
    json_path: Path
    env_id: str
    control_mode: str
    episodes: list[dict]
    env_kwargs: dict


def open_trajectory_file(h5_path: str | Path, json_path: str | Path | None = None) -> TrajectoryFile:
    """Check that the pair of files is complete and describes images; raise a ValueError naming the fault."""
    h5_path = Path(h5_path)
    json_path = Path(json_path) if json_path else h5_path.with_suffix(".json")
    if not h5_path.exists():
        raise MissingInputError(f"{h5_path}: no such trajectory file")
    if not json_path.exists():
        raise MissingInputError(
            f"{json_path}: missing; ManiSkill writes it beside {h5_path.name} and it is needed for the episode list"
        )
    try:
        with open(json_path) as f:
            meta = json.load(f)
        env_info, episodes = meta["env_info"], meta["episodes"]
    except (json.JSONDecodeError, KeyError, TypeError) as e:
        raise InvalidInputError(f"{json_path}: not a ManiSkill trajectory .json ({type(e).__name__}: {e})") from e
    if not episodes:
        raise InvalidInputError(f"{json_path}: lists no episodes")
    env_kwargs = env_info.get("env_kwargs", {})
    control_mode = env_kwargs.get("control_mode") or episodes[0].get("control_mode")
    try:
        h5 = h5py.File(h5_path, "r")
    except OSError as e:
        raise InvalidInputError(f"{h5_path}: cannot be read as HDF5 (truncated or corrupt?): {e}") from e
    with h5:
        for episode in episodes:
            _check_episode(h5, h5_path, episode)
    return TrajectoryFile(h5_path, json_path, env_info["env_id"], control_mode or "unknown", episodes, env_kwargs)


def _check_episode(h5: h5py.File, h5_path: Path, episode: dict) -> None:
    key = f"traj_{episode['episode_id']}"
    where = f"{h5_path} episode {episode['episode_id']}"
    if key not in h5:
        raise InvalidInputError(f"{where}: group {key!r} listed in the .json is missing from the .h5 (truncated file?)")
    group = h5[key]
    if "actions" not in group:
        raise InvalidInputError(f"{where}: has no 'actions' dataset")
    try:
        n = group["actions"].shape[0]
        cameras = _cameras(group)
        if not cameras:
            raise InvalidInputError(f"{where}: " + RENDER_HINT.format(h5=h5_path))
        for name, rgb in cameras.items():
            if rgb.ndim != 4 or rgb.shape[-1] != 3 or rgb.shape[0] != n + 1:
                raise InvalidInputError(
                    f"{where}: camera {name!r} has shape {rgb.shape}; expected ({n + 1}, H, W, 3) for {n} actions"
                )
        for flag in ("success", "terminated", "truncated"):
            if flag in group and group[flag].shape[0] != n:
                raise InvalidInputError(f"{where}: {flag!r} has {group[flag].shape[0]} entries for {n} actions")
    except (OSError, RuntimeError, KeyError) as e:  # h5py raises these on truncated chunks
        raise InvalidInputError(f"{where}: unreadable data (truncated file?): {e}") from e


def _cameras(group: h5py.Group) -> dict[str, h5py.Dataset]:
    sensors = group.get("obs/sensor_data")
    if sensors is None:
        return {}
    return {name: sensors[name]["rgb"] for name in sensors if "rgb" in sensors[name]}


def _state(group: h5py.Group, n: int) -> np.ndarray:
    """Joint positions, plus the TCP pose where the file recorded it."""
    parts = []
    if "obs/agent/qpos" in group:
        parts.append(group["obs/agent/qpos"][:n])
    if "obs/extra/tcp_pose" in group:
        parts.append(group["obs/extra/tcp_pose"][:n])
    if not parts:
        return np.zeros((n, 0), dtype=np.float32)
    return np.concatenate(parts, axis=1).astype(np.float32)


def read_episodes(traj: TrajectoryFile, task: str, camera_names: dict[str, str] | None = None) -> Iterator[Episode]:
    """Every episode of the file, in the .json's order; frame counts, actions and success flags as recorded."""
    camera_names = camera_names or {}
    with h5py.File(traj.h5_path, "r") as h5:
        for meta in traj.episodes:
            group = h5[f"traj_{meta['episode_id']}"]
            where = f"{traj.h5_path} episode {meta['episode_id']}"
            try:
                actions = group["actions"][:].astype(np.float32)
                n = len(actions)
                images = {camera_names.get(name, name): rgb[:n] for name, rgb in _cameras(group).items()}
                success = group["success"][:].astype(bool) if "success" in group else np.zeros(n, dtype=bool)
                if "success" not in group and meta.get("success"):
                    success[-1] = True
                done = np.zeros(n, dtype=bool)
                for flag in ("terminated", "truncated"):
                    if flag in group:
                        done |= group[flag][:].astype(bool)
                done[-1] = True
                reward = group["rewards"][:].astype(np.float32) if "rewards" in group else np.zeros(n, np.float32)
                state = _state(group, n)
            except (OSError, RuntimeError, KeyError) as e:
                raise InvalidInputError(f"{where}: unreadable data (truncated file?): {e}") from e
            episode = Episode(
                images,
                state,
                actions,
                reward,
                success,
                done,
                task,
                info={
                    "source_file": traj.h5_path.name,
                    "source_episode_id": meta["episode_id"],
                    "env_id": traj.env_id,
                    "control_mode": traj.control_mode,
                    "seed": meta.get("episode_seed"),
                    "success": bool(success[-1]),
                },
            )
            episode.validate(where)
            yield episode
