"""Controllability sets (`roboscape-collect-control`): one start, several action sequences, each replayed in the
simulator from the same initial state.

For each start (family, scene, seed) the planner runs for `steps` actions: that is sequence 0. Sequences 1..K-1
replay sequence 0's actions open loop, each with its own constant offset added to the TCP translation (a random
direction of length `offset`), so the arm drifts a different way in each while doing the same thing otherwise.
A world model that follows its actions must tell the K futures apart from the same first frames
(world_model/measures/controllability.py). Episodes record which start and sequence they are (`start`, `sequence`).
"""

import logging
import shutil
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from lerobot_roboscape.dataset.episode import Episode
from lerobot_roboscape.dataset.writer import check_target
from lerobot_roboscape.demos.collect import saved_jobs, write_task_dataset
from lerobot_roboscape.demos.rollout import EpisodeJob, replay_actions, run_jobs, run_planned_episode, worker_env
from lerobot_roboscape.tasks import TASK_FAMILIES, select_scenes
from roboscape_core.errors import InvalidInputError

TRANSLATION = slice(0, 3)  # the action's TCP translation (dx, dy, dz), what the offsets move


@dataclass
class ControllabilityConfig:
    """Args:
    repo_id: dataset name recorded in its metadata.
    root: output directory; must not exist unless `overwrite`.
    families: task families.
    split: scenes of this split ("ood": scenes no model trained on).
    max_scenes: the first N scenes of the split.
    starts_per_scene: starts per (family, scene).
    sequences: action sequences per start (K), the planner's and K - 1 offset replays.
    steps: actions per sequence (the world model's prompt frames plus the horizon it is measured on).
    offset: length of each replay's translation offset, in normalised action units (actions are in [-1, 1]).
    seed: base seed; start k uses seed + k.
    image_size: camera resolution.
    workers: parallel ManiSkill processes (1 or fewer: in this process).
    overwrite: replace an existing dataset at `root`.
    resume: continue an interrupted collection into `root` from the starts it saved.
    """

    repo_id: str = "local/roboscape_controllability"
    root: str = "outputs/datasets/roboscape_controllability"
    families: list[str] = field(default_factory=lambda: list(TASK_FAMILIES))
    split: str = "ood"
    max_scenes: int | None = 8
    starts_per_scene: int = 2
    sequences: int = 4
    steps: int = 49  # the reports' longest horizon (48 control steps) after the first frame
    offset: float = 0.6
    seed: int = 70_000
    image_size: int = 64
    workers: int = 2
    overwrite: bool = False
    resume: bool = False

    def __post_init__(self):
        if self.sequences < 2:
            raise InvalidInputError(f"sequences must be >= 2 (one to retrieve among others), got {self.sequences}")
        if self.steps < 2:
            raise InvalidInputError(f"steps must be >= 2, got {self.steps}")


@dataclass(frozen=True)
class StartJob:
    job: EpisodeJob
    start: int
    sequences: int
    steps: int
    offset: float


def offsets(seed: int, sequences: int, length: float) -> np.ndarray:
    """(sequences, 3) translation offsets: none for sequence 0, then directions of `length` spread evenly in
    azimuth (from a random first one), so that no two replays drift the same way."""
    rng = np.random.default_rng(seed)
    out = np.zeros((sequences, 3), dtype=np.float32)
    azimuths = (np.arange(sequences - 1) + rng.uniform(0, 1)) * 2 * np.pi / (sequences - 1)
    for k, azimuth in enumerate(azimuths, start=1):
        elevation = rng.uniform(-0.4, 0.4)
        out[k] = length * np.array(
            [np.cos(azimuth) * np.cos(elevation), np.sin(azimuth) * np.cos(elevation), np.sin(elevation)]
        )
    return out


def run_start(task: StartJob) -> list[Episode]:
    """The K episodes of one start (run in a worker process)."""
    env = worker_env(task.job)
    planned = run_planned_episode(env, task.job)
    actions = planned.action[: task.steps]
    if len(actions) < task.steps:  # a plan that ends early holds its last action
        actions = np.concatenate([actions, np.repeat(actions[-1:], task.steps - len(actions), 0)])
    episodes = []
    for k, offset in enumerate(offsets(task.job.seed, task.sequences, task.offset)):
        perturbed = actions.copy()
        perturbed[:, TRANSLATION] = np.clip(perturbed[:, TRANSLATION] + offset, -1.0, 1.0)
        facts = {
            "start": task.start,
            "sequence": k,
            "offset": [round(float(v), 4) for v in offset],
            "kind": "controllability",
        }
        episodes.append(replay_actions(env, task.job, perturbed, facts))
    return episodes


def make_start_jobs(cfg: ControllabilityConfig) -> list[StartJob]:
    scenes = select_scenes(cfg.split)[: cfg.max_scenes]
    if not scenes:
        raise InvalidInputError(f"no scene matches split={cfg.split!r}")
    jobs = []
    for family in cfg.families:
        for scene in scenes:
            for _ in range(cfg.starts_per_scene):
                job = EpisodeJob(family, scene.id, cfg.seed + len(jobs), "optimal", cfg.image_size, segmentation=True)
                jobs.append(StartJob(job, len(jobs), cfg.sequences, cfg.steps, cfg.offset))
    return jobs


def collect_controllability(cfg: ControllabilityConfig):
    """Run every start's sequences and write them as one dataset at `cfg.root` (atomically, once all are run). Each
    finished start's episodes are saved beside the target at once, so a killed run continues with --resume=true."""
    root = Path(cfg.root).resolve()
    check_target(root, cfg.overwrite)
    jobs = make_start_jobs(cfg)
    work = saved_jobs(root, [asdict(job) for job in jobs], cfg.resume)
    files = [[work / f"{k:06d}-{sequence}.npz" for sequence in range(cfg.sequences)] for k in range(len(jobs))]
    todo = [k for k in range(len(jobs)) if not all(file.exists() for file in files[k])]
    logging.info(
        "controllability set: %d of %d starts x %d sequences of %d steps",
        len(todo),
        len(jobs),
        cfg.sequences,
        cfg.steps,
    )
    started = run_jobs([jobs[k] for k in todo], cfg.workers, run_start)
    for k, start_episodes in tqdm(zip(todo, started, strict=True), total=len(todo), desc="starts"):
        for file, episode in zip(files[k], start_episodes, strict=True):
            episode.save(file)
    dataset = write_task_dataset(
        (Episode.load(file) for start in files for file in start),
        cfg.repo_id,
        root,
        overwrite=cfg.overwrite,
        total=len(jobs) * cfg.sequences,
    )
    shutil.rmtree(work)
    return dataset
