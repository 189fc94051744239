"""Planner demonstrations in the task suite, collected into a LeRobotDataset v3 (`roboscape-collect`)."""

import json
import logging
import os
import shutil
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from tqdm import tqdm

from lerobot_roboscape.dataset.episode import Episode
from lerobot_roboscape.dataset.writer import check_target, write_dataset
from lerobot_roboscape.demos.exploration import EXPLORATORY_KINDS
from lerobot_roboscape.demos.planner import KINDS
from lerobot_roboscape.demos.rollout import EpisodeJob, run_jobs
from lerobot_roboscape.io.atomic import make_tmp_dir
from lerobot_roboscape.robot import ACTION_NAMES, CONTROL_FREQ, STATE_NAMES
from lerobot_roboscape.tasks import TASK_FAMILIES, select_scenes
from roboscape_core.errors import InvalidInputError, OutputExistsError

JOBS = "jobs.json"  # the planned episodes of an interrupted collection, which a resumed one must equal


def episodes_dir(root: Path) -> Path:
    """Where a collection into `root` saves each finished episode until the dataset is written."""
    root = Path(root).resolve()
    return root.parent / f".{root.name}.episodes"


def saved_jobs(root: Path, plan: list[dict], resume: bool) -> Path:
    """The folder where a collection into `root` saves each finished job's episodes until the dataset is written
    (`episodes_dir`): made for `plan`, or the one an interrupted collection left, taken if `resume` and its plan is
    `plan`."""
    work = episodes_dir(root)
    if work.exists():
        if not resume:
            raise OutputExistsError(
                f"{work} holds an interrupted collection for {root}: pass --resume=true to "
                "continue it, or delete it to start over"
            )
        if json.loads((work / JOBS).read_text()) != plan:
            raise InvalidInputError(
                f"--resume=true: {work} was collected with other settings (families, scenes, "
                "episodes, fractions, seed or image size); use them, or delete it to start over"
            )
    else:
        root.parent.mkdir(parents=True, exist_ok=True)
        staging = make_tmp_dir(root.parent, f"{root.name}.episodes")
        (staging / JOBS).write_text(json.dumps(plan))
        os.replace(staging, work)
    return work


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
    kinds: deal these plan kinds evenly instead of the fractions above. The exploratory kinds (noisy, excursion,
        random: demos/exploration.py) make a dataset of their own for the action world model, never mixed with the
        demonstrations that SFT imitates.
    seed: base seed; episode k of the run uses seed + k.
    image_size: square camera resolution for both cameras.
    workers: parallel ManiSkill processes (1 or fewer: run in this process).
    light_wrist_camera: render the wrist camera's body with a light mesh (3.5x faster without a GPU; the frames
        differ only on its outline); false renders ManiSkill's own mesh.
    segmentation: also record each frame's masks of the task object and the container, stored beside the dataset
        (dataset/segmentation.py); the tokenizer and world-model reports measure the object on them, and the
        tokenizer can weigh its loss by them. About a quarter slower.
    keep_failed: also write attempts that did not succeed (in the simulator, whatever their kind).
    overwrite: replace an existing dataset at `root`.
    resume: continue an interrupted collection into `root` from the episodes it saved.
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
    kinds: list[str] | None = None
    seed: int = 0
    image_size: int = 64
    workers: int = 2
    light_wrist_camera: bool = True
    segmentation: bool = False
    keep_failed: bool = True
    overwrite: bool = False
    resume: bool = False
    list_scenes: bool = False

    def __post_init__(self):
        unknown = [f for f in self.families if f not in TASK_FAMILIES]
        if unknown:
            raise InvalidInputError(f"Unknown task families {unknown}; expected a subset of {list(TASK_FAMILIES)}")
        if not 0.0 <= self.failed_fraction <= 1.0:
            raise InvalidInputError(f"failed_fraction must be in [0, 1], got {self.failed_fraction}")
        if not 0.0 <= self.suboptimal_fraction <= 1.0:
            raise InvalidInputError(f"suboptimal_fraction must be in [0, 1], got {self.suboptimal_fraction}")
        if self.kinds is not None:
            if not self.kinds or (unknown := [k for k in self.kinds if k not in KINDS + EXPLORATORY_KINDS]):
                raise InvalidInputError(
                    f"kinds must name plan kinds among {list(KINDS + EXPLORATORY_KINDS)}, got {self.kinds}"
                )
            if set(self.kinds) & set(EXPLORATORY_KINDS) and set(self.kinds) & set(KINDS):
                raise InvalidInputError(
                    f"kinds={self.kinds} mixes exploratory kinds with demonstrations: exploratory episodes go in a "
                    "dataset of their own (SFT and lerobot-train's statistics must not see them)"
                )
        if self.episodes_per_scene < 1:
            raise InvalidInputError(f"episodes_per_scene must be >= 1, got {self.episodes_per_scene}")
        if self.image_size < 16:
            raise InvalidInputError(f"image_size must be >= 16, got {self.image_size}")


def make_jobs(cfg: CollectConfig) -> list[EpisodeJob]:
    scenes = select_scenes(cfg.split, cfg.scenes)
    if cfg.max_scenes is not None and not cfg.scenes:
        scenes = scenes[: cfg.max_scenes]
    if not scenes:
        raise InvalidInputError(f"No scene matches split={cfg.split!r} scenes={cfg.scenes}")
    rng = np.random.default_rng(cfg.seed)
    # Kinds are dealt over all episodes of a family, not per scene: a few episodes per scene would round a small
    # failed_fraction down to no failure at all.
    n = len(scenes) * cfg.episodes_per_scene
    if cfg.kinds:
        deck = [cfg.kinds[i % len(cfg.kinds)] for i in range(n)]
    else:
        n_failed = round(n * cfg.failed_fraction)
        n_sub = round((n - n_failed) * cfg.suboptimal_fraction)
        deck = ["failed"] * n_failed + ["suboptimal"] * n_sub + ["optimal"] * (n - n_failed - n_sub)
    jobs = []
    for family in cfg.families:
        kinds = iter(rng.permutation(deck))
        for scene in scenes:
            for _ in range(cfg.episodes_per_scene):
                jobs.append(
                    EpisodeJob(
                        family,
                        scene.id,
                        cfg.seed + len(jobs),
                        str(next(kinds)),
                        cfg.image_size,
                        cfg.light_wrist_camera,
                        cfg.segmentation,
                    )
                )
    return jobs


def collect(cfg: CollectConfig) -> LeRobotDataset:
    """Run the planner jobs and write their episodes as a dataset at `cfg.root`.

    Each finished episode is saved at once beside the target (`.<root>.episodes/`), so a killed run continues with
    --resume=true from the episodes it had; the dataset is written, atomically, once all of them exist.
    """
    jobs = make_jobs(cfg)
    root = Path(cfg.root).resolve()
    check_target(root, cfg.overwrite)  # before hours of collection, not after
    work = saved_jobs(root, [asdict(job) for job in jobs], cfg.resume)
    files = [work / f"{k:06d}.npz" for k in range(len(jobs))]
    todo = [k for k, file in enumerate(files) if not file.exists()]
    logging.info(
        "Collecting %d of %d episodes over %d families with %d workers",
        len(todo),
        len(jobs),
        len(cfg.families),
        cfg.workers,
    )
    episodes = run_jobs([jobs[k] for k in todo], cfg.workers)
    for k, episode in tqdm(zip(todo, episodes, strict=True), total=len(todo), desc="collecting", unit="episode"):
        episode.save(files[k])
    dataset = write_task_dataset(
        (Episode.load(file) for file in files),
        cfg.repo_id,
        root,
        overwrite=cfg.overwrite,
        total=len(jobs),
        keep=lambda episode: cfg.keep_failed or episode.succeeded,
    )
    shutil.rmtree(work)
    return dataset


def write_task_dataset(episodes, repo_id: str, root: Path, **kwargs) -> LeRobotDataset:
    """`write_dataset` with the task suite's rate, state and action names and robot."""
    return write_dataset(
        episodes,
        repo_id,
        root,
        fps=CONTROL_FREQ,
        state_names=STATE_NAMES,
        action_names=ACTION_NAMES,
        robot_type="panda",
        **kwargs,
    )
