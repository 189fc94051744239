"""`roboscape-collect`: planner demonstrations in the task suite, written as a LeRobotDataset v3.

    roboscape-collect --families='[pick_place,push]' --split=ind --episodes_per_scene=4 \
        --failed_fraction=0.25 --suboptimal_fraction=0.5 --root=outputs/datasets/demos
"""

import logging
from dataclasses import dataclass, field
from pathlib import Path

import draccus
import numpy as np

from lerobot_roboscape.dataset import write_dataset
from lerobot_roboscape.demos.rollout import EpisodeJob, run_jobs
from lerobot_roboscape.tasks import SCENES, TASK_FAMILIES, select_scenes

STATE_NAMES = [f"joint_{i}" for i in range(7)] + ["finger_left", "finger_right"] + [
    "tcp_x", "tcp_y", "tcp_z", "tcp_qw", "tcp_qx", "tcp_qy", "tcp_qz"]
ACTION_NAMES = ["dx", "dy", "dz", "drx", "dry", "drz", "gripper"]
CONTROL_FREQ = 20  # Hz, the ManiSkill tabletop default


@dataclass
class CollectConfig:
    """Args:
    repo_id: dataset name (`user/name`) recorded in its metadata and used when pushing.
    root: output directory; must not exist unless `overwrite`.
    families: task families to collect.
    split: scenes of this split ("ind", "ood" or "all").
    scenes: explicit scene ids (overrides `max_scenes`; still filtered by `split`).
    max_scenes: use only the first N scenes of the split (None: all).
    episodes_per_scene: episodes per (family, scene).
    failed_fraction: share of deliberately failed attempts (a grasp or push beside the object, the object put
        down or pushed short of its target), dealt per family: the world model must see what failure looks like.
    suboptimal_fraction: share of suboptimal trajectories among the other attempts (the rest are optimal).
    seed: base seed; episode k of the run uses seed + k.
    image_size: square camera resolution for both cameras.
    workers: parallel ManiSkill processes (0: run in this process).
    keep_failed: also write attempts that did not succeed (in the simulator, whatever their kind).
    overwrite: replace an existing dataset at `root`.
    list_scenes: print the scenes with their split and exit.
    """

    repo_id: str = "local/roboscape_demos"
    root: str = "outputs/datasets/roboscape_demos"
    families: list[str] = field(default_factory=lambda: list(TASK_FAMILIES))
    split: str = "ind"
    scenes: list[str] | None = None
    max_scenes: int | None = None
    episodes_per_scene: int = 2
    failed_fraction: float = 0.25
    suboptimal_fraction: float = 0.5
    seed: int = 0
    image_size: int = 64
    workers: int = 2
    keep_failed: bool = True
    overwrite: bool = False
    list_scenes: bool = False

    def __post_init__(self):
        unknown = [f for f in self.families if f not in TASK_FAMILIES]
        if unknown:
            raise ValueError(f"Unknown task families {unknown}; expected a subset of {list(TASK_FAMILIES)}")
        if not 0.0 <= self.failed_fraction <= 1.0:
            raise ValueError(f"failed_fraction must be in [0, 1], got {self.failed_fraction}")
        if not 0.0 <= self.suboptimal_fraction <= 1.0:
            raise ValueError(f"suboptimal_fraction must be in [0, 1], got {self.suboptimal_fraction}")
        if self.episodes_per_scene < 1:
            raise ValueError(f"episodes_per_scene must be >= 1, got {self.episodes_per_scene}")
        if self.image_size < 16:
            raise ValueError(f"image_size must be >= 16, got {self.image_size}")


def make_jobs(cfg: CollectConfig) -> list[EpisodeJob]:
    scenes = select_scenes(cfg.split, cfg.scenes)
    if cfg.max_scenes is not None and not cfg.scenes:
        scenes = scenes[: cfg.max_scenes]
    if not scenes:
        raise ValueError(f"No scene matches split={cfg.split!r} scenes={cfg.scenes}")
    rng = np.random.default_rng(cfg.seed)
    # Kinds are dealt over all episodes of a family, not per scene: a few episodes per scene would round a small
    # failed_fraction down to no failure at all.
    n = len(scenes) * cfg.episodes_per_scene
    n_failed = round(n * cfg.failed_fraction)
    n_sub = round((n - n_failed) * cfg.suboptimal_fraction)
    deck = ["failed"] * n_failed + ["suboptimal"] * n_sub + ["optimal"] * (n - n_failed - n_sub)
    jobs = []
    for family in cfg.families:
        kinds = iter(rng.permutation(deck))
        for scene in scenes:
            for _ in range(cfg.episodes_per_scene):
                jobs.append(EpisodeJob(family, scene.id, cfg.seed + len(jobs), str(next(kinds)), cfg.image_size))
    return jobs


def collect(cfg: CollectConfig):
    jobs = make_jobs(cfg)
    logging.info("Collecting %d episodes over %d families with %d workers", len(jobs), len(cfg.families), cfg.workers)
    return write_dataset(
        run_jobs(jobs, cfg.workers), cfg.repo_id, cfg.root, fps=CONTROL_FREQ, state_names=STATE_NAMES,
        action_names=ACTION_NAMES, robot_type="panda", overwrite=cfg.overwrite, total=len(jobs),
        keep=lambda episode: cfg.keep_failed or episode.succeeded,
    )


def main(argv: list[str] | None = None):
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    cfg = draccus.parse(CollectConfig, args=argv)
    if cfg.list_scenes:
        for scene in SCENES:
            print(f"{scene.id:40s} {scene.split}")
        return
    dataset = collect(cfg)
    meta = dataset.meta
    print(f"Wrote {meta.total_episodes} episodes, {meta.total_frames} frames to {Path(cfg.root).resolve()}")


if __name__ == "__main__":
    main()
