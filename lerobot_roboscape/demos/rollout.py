"""Planner rollouts in the task suite, spread over worker processes (one ManiSkill env per family each)."""

import multiprocessing as mp
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np
import torch

from lerobot_roboscape.dataset.episode import Episode
from lerobot_roboscape.dataset.segmentation import label_image
from lerobot_roboscape.demos.exploration import EXPLORATORY_KINDS, explore_episode
from lerobot_roboscape.demos.planner import FailureConfig, SuboptimalConfig, plan_episode
from lerobot_roboscape.robot import CAMERA_NAMES
from lerobot_roboscape.tasks.base import RoboscapeTabletopEnv
from lerobot_roboscape.tasks.make import make_task_env

SETTLE_STEPS = 3  # control steps after the plan ends, so the last frames show the finished task at rest
# Suboptimal plans with detours at low speed outlast the tasks' RL time limits; the plan ends the episode.
COLLECT_MAX_STEPS = 320


@dataclass(frozen=True)
class EpisodeJob:
    family: str
    scene_id: str
    seed: int
    kind: str  # of the plan: one of planner.KINDS (demonstrations) or exploration.EXPLORATORY_KINDS
    image_size: int
    light_wrist_camera: bool = True  # render the wrist camera's body with the light mesh (tasks/wrist_camera_mesh.py)
    segmentation: bool = (
        False  # also record the object's, the container's and the robot's masks (dataset/segmentation.py)
    )


def observation_state(obs: dict) -> np.ndarray:
    """Joint positions (9) + TCP pose (7: xyz, quaternion wxyz) of env 0."""
    qpos = obs["agent"]["qpos"][0].cpu().numpy()
    tcp = obs["extra"]["tcp_pose"][0].cpu().numpy()
    return np.concatenate([qpos, tcp]).astype(np.float32)


def observation_images(obs: dict) -> dict[str, np.ndarray]:
    return {CAMERA_NAMES[uid]: data["rgb"][0].cpu().numpy() for uid, data in obs["sensor_data"].items()}


def observation_masks(obs: dict, task_env: RoboscapeTabletopEnv) -> dict[str, np.ndarray]:
    """camera -> (H, W) labels of the object, the container and the robot, from an observation with segmentation."""
    object_id, container_id = int(task_env.obj.per_scene_id[0]), int(task_env.container.per_scene_id[0])
    robot_ids = tuple(int(link.per_scene_id[0]) for link in task_env.agent.robot.links)
    return {
        CAMERA_NAMES[uid]: label_image(
            data["segmentation"][0, ..., 0].cpu().numpy(), object_id, container_id, robot_ids
        )
        for uid, data in obs["sensor_data"].items()
    }


class EpisodeRecorder:
    """The frames of one episode as it runs: each observation before its action, and what followed the action."""

    def __init__(self, task_env: RoboscapeTabletopEnv, segmentation: bool):
        self.task_env, self.segmentation = task_env, segmentation
        self.frames: dict[str, list] = {k: [] for k in ("state", "action", "reward", "success", "images", "masks")}

    def observe(self, obs: dict) -> None:
        self.frames["images"].append(observation_images(obs))
        if self.segmentation:
            self.frames["masks"].append(observation_masks(obs, self.task_env))
        self.frames["state"].append(observation_state(obs))

    def acted(self, action: np.ndarray, reward, info: dict) -> None:
        self.frames["action"].append(action)
        self.frames["reward"].append(float(reward[0]))
        self.frames["success"].append(bool(info["success"][0]))

    def episode(self, info: dict) -> Episode:
        frames = self.frames
        done = np.zeros(len(frames["action"]), dtype=bool)
        done[-1] = True
        cameras = frames["images"][0].keys()
        episode = Episode(
            images={cam: np.stack([f[cam] for f in frames["images"]]) for cam in cameras},
            state=np.stack(frames["state"]),
            action=np.stack(frames["action"]),
            reward=np.asarray(frames["reward"], dtype=np.float32),
            success=np.asarray(frames["success"], dtype=bool),
            done=done,
            task=self.task_env.instruction,
            masks={cam: np.stack([f[cam] for f in frames["masks"]]) for cam in cameras} if self.segmentation else None,
            info={"scene": self.task_env.scene_spec.id, "split": self.task_env.scene_spec.split, **info},
        )
        episode.info["success"] = episode.succeeded
        return episode


def run_planned_episode(
    env, job: EpisodeJob, suboptimal: SuboptimalConfig | None = None, failure: FailureConfig | None = None
) -> Episode:
    """Reset `env` (a task env of `job.family`) into `job.scene_id` and follow a planned trajectory to its end."""
    obs, _ = env.reset(seed=job.seed, options={"scene_id": job.scene_id})
    task_env: RoboscapeTabletopEnv = env.unwrapped
    rng = np.random.default_rng(job.seed)
    if job.kind in EXPLORATORY_KINDS:
        follower = explore_episode(task_env, job.kind, rng)
    else:
        follower = plan_episode(task_env, job.kind, rng, suboptimal, failure)
    recorder = EpisodeRecorder(task_env, job.segmentation)
    settle = SETTLE_STEPS
    while True:
        tcp = task_env.agent.tcp_pose
        action = follower.act(tcp.p[0].cpu().numpy(), tcp.q[0].cpu().numpy())
        recorder.observe(obs)
        obs, reward, terminated, truncated, info = env.step(action)
        recorder.acted(action, reward, info)
        if follower.done:
            settle -= 1
        if settle <= 0 or bool(truncated[0]):
            break
    return recorder.episode(
        {
            "task_family": job.family,
            "optimal": job.kind == "optimal",
            "kind": job.kind,
            "seed": job.seed,
            "skipped_waypoints": follower.skipped,
            **({"departures": follower.departures} if job.kind in EXPLORATORY_KINDS else {}),
        }
    )


def replay_actions(env, job: EpisodeJob, actions: np.ndarray, info: dict) -> Episode:
    """Reset `env` into `job`'s scene and initial state (its seed) and apply `actions` (T, A) open loop."""
    obs, _ = env.reset(seed=job.seed, options={"scene_id": job.scene_id})
    recorder = EpisodeRecorder(env.unwrapped, job.segmentation)
    for action in actions:
        recorder.observe(obs)
        obs, reward, _, _, step_info = env.step(action)
        recorder.acted(action, reward, step_info)
    return recorder.episode({"task_family": job.family, "seed": job.seed, **info})


# Worker processes keep one env per family and switch scenes by reset options (a scene rebuild, no new env).
_worker_envs: dict = {}


def worker_env(job: EpisodeJob):
    """This process's env for the job's family and camera settings, made on first use."""
    key = (job.family, job.image_size, job.light_wrist_camera, job.segmentation)
    if key not in _worker_envs:
        _worker_envs[key] = make_task_env(
            job.family,
            job.scene_id,
            image_size=job.image_size,
            obs_mode="rgb+segmentation" if job.segmentation else "rgb",
            max_episode_steps=COLLECT_MAX_STEPS,
            light_wrist_camera=job.light_wrist_camera,
        )
    return _worker_envs[key]


def _worker_run(job: EpisodeJob) -> Episode:
    return run_planned_episode(worker_env(job), job)


def _one_thread() -> None:
    # The controllers' tensors are tiny: with torch's default of a thread per core, the workers' threads fight over
    # the cores (pick&place, 2 workers on 2 cores: 15.5 episodes/min, 18.7 with one thread each).
    torch.set_num_threads(1)


def run_jobs(jobs: list, workers: int = 2, run: Callable = _worker_run) -> Iterator:
    """`run(job)` of each job, in order, computed by `workers` processes (1 or fewer: in this process, as the
    simulator's slots do; a pool of one would only add a process's start-up); `run` must be a module-level function
    (it is sent to the workers by name)."""
    if workers <= 1:
        for job in jobs:
            yield run(job)
        return
    # SAPIEN's renderer does not survive fork; spawn clean interpreters.
    with mp.get_context("spawn").Pool(workers, initializer=_one_thread) as pool:
        yield from pool.imap(run, jobs, chunksize=1)
