"""Official ManiSkill trajectory files (.h5 + .json) converted to a LeRobotDataset v3 (`roboscape-convert`)."""

import logging
from dataclasses import dataclass

from lerobot_roboscape.dataset.maniskill_files import open_trajectory_file, read_episodes
from lerobot_roboscape.dataset.writer import write_dataset
from lerobot_roboscape.robot import CAMERA_NAMES, CONTROL_FREQ
from lerobot_roboscape.tasks import ENV_IDS, get_scene
from roboscape_core.errors import InvalidInputError


@dataclass
class ConvertConfig:
    """Args:
    h5: the ManiSkill trajectory file.
    json: its episode list (default: the .h5 path with .json).
    repo_id: dataset name recorded in its metadata.
    root: output directory; must not exist unless `overwrite`.
    task: instruction stored with every frame (default: the scene's instruction for roboscape tasks, else the env id).
    fps: frames per second (ManiSkill tabletop tasks control at 20 Hz).
    overwrite: replace an existing dataset at `root`.
    """

    h5: str = ""
    json: str | None = None
    repo_id: str = "local/maniskill_converted"
    root: str = "outputs/datasets/maniskill_converted"
    task: str | None = None
    fps: int = CONTROL_FREQ
    overwrite: bool = False


def default_task(env_id: str, env_kwargs: dict) -> str:
    family = {v: k for k, v in ENV_IDS.items()}.get(env_id)
    if family and "scene_id" in env_kwargs:
        return get_scene(env_kwargs["scene_id"]).instruction(family)
    logging.warning("No --task given: using the env id %r as the instruction", env_id)
    return env_id


def convert(cfg: ConvertConfig):
    if not cfg.h5:
        raise InvalidInputError("--h5 is required (the ManiSkill trajectory file to convert)")
    traj = open_trajectory_file(cfg.h5, cfg.json)
    task = cfg.task or default_task(traj.env_id, traj.env_kwargs)
    return write_dataset(
        read_episodes(traj, task, camera_names=CAMERA_NAMES),
        cfg.repo_id,
        cfg.root,
        fps=cfg.fps,
        overwrite=cfg.overwrite,
        total=len(traj.episodes),
    )
