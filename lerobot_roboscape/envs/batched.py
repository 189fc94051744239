"""What the two env types share: a batched gymnasium VectorEnv that LeRobot's evaluation can drive, and the
episode bookkeeping of the paper's objective (Algorithm 1)."""

import gymnasium as gym
import numpy as np
import torch
from gymnasium.vector import AutoresetMode

from lerobot_roboscape.robot import CONTROL_FREQ


def start_groups(slot_families: list[str], group_size: int) -> np.ndarray:
    """The group of each of the B episodes when `reset(options={"group_size": G})` starts G of them from one start
    (the same scene and initial state: GRPO's group of rollouts): groups of G slots of one task family, taken in slot
    order. group_size 1: every episode its own group."""
    if group_size < 1:
        raise ValueError(f"group_size must be >= 1, got {group_size}")
    groups = np.empty(len(slot_families), dtype=np.int64)
    for family in dict.fromkeys(slot_families):
        slots = [i for i, f in enumerate(slot_families) if f == family]
        if len(slots) % group_size:
            raise ValueError(
                f"group_size={group_size} does not divide the {len(slots)} parallel episodes of task family "
                f"{family!r} ({len(slot_families)} in all, the families dealt in turn): choose num_envs as a "
                "multiple of group_size x the number of families"
            )
        for k, i in enumerate(slots):
            groups[i] = k // group_size
    # Number the groups in the order of their first slot.
    keys = [(slot_families[i], groups[i]) for i in range(len(slot_families))]
    ids = {key: n for n, key in enumerate(dict.fromkeys(keys))}
    return np.array([ids[key] for key in keys], dtype=np.int64)


class BatchedEnv(gym.vector.VectorEnv):
    """B episodes stepped together. Autoreset is off: an ended episode stays frozen until `reset()`, which restarts
    all of them (LeRobot's evaluation and our PPO reset whole batches). Subclasses define `tasks()`, the
    instruction of each episode."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": CONTROL_FREQ, "autoreset_mode": AutoresetMode.DISABLED}

    def _seed_from(self, seed, options) -> int | None:
        if (options or {}).get("reset_mask") is not None and not np.all(options["reset_mask"]):
            raise ValueError(f"{type(self).__name__} resets all its episodes together; pass no reset_mask")
        if seed is None:
            return None
        return int(seed[0] if isinstance(seed, (list, tuple, np.ndarray)) else seed)

    def _check_actions(self, actions) -> tuple[np.ndarray, np.ndarray]:
        """Actions as float32 (B, action_dim), clipped to [-1, 1], and the count of clipped values per env."""
        actions = np.asarray(actions.detach().cpu() if torch.is_tensor(actions) else actions, dtype=np.float32)
        if actions.shape != self.action_space.shape:
            raise ValueError(
                f"{type(self).__name__} expects actions of shape {self.action_space.shape} "
                f"(num_envs, action_dim), got {actions.shape}"
            )
        bad = ~np.isfinite(actions).all(axis=1)
        if bad.any():
            raise ValueError(f"actions of envs {np.flatnonzero(bad).tolist()} contain NaN or inf: {actions[bad]}")
        return np.clip(actions, -1.0, 1.0), np.count_nonzero(np.abs(actions) > 1.0, axis=1)

    # gymnasium 1.x VectorEnv has no call/get_attr; LeRobot's evaluation uses them.
    def call(self, name: str, *args, **kwargs) -> tuple:
        if name == "render":
            return self.render()
        if name in ("task", "task_description"):
            return self.tasks()
        value = getattr(self, name)
        value = value(*args, **kwargs) if callable(value) else value
        return (value,) * self.num_envs

    def get_attr(self, name: str) -> tuple:
        return self.call(name)


class EpisodeBook:
    """Per-episode bookkeeping of a batch, the same in both env types.

    By default (paper Algorithm 1) every episode runs its fixed horizon and never terminates: success is the task
    done at any step (`is_success` stays true once reached), and the env keeps paying its reward, so reaching the
    goal early and staying there earns the most. With `terminate_on_success`, an episode ends at its first success
    and that step also pays `max_step_reward` for every step left in its horizon: no continuation can earn more
    than that, so success is never worth less than failure, whatever the per-step reward pays elsewhere.

    Args:
        horizons: (B,) steps of each episode before truncation.
        terminate_on_success: end an episode at its first success.
        max_step_reward: the most one step can pay (the terminal bonus's rate).
    """

    def __init__(self, horizons: np.ndarray, terminate_on_success: bool, max_step_reward: float):
        self.horizons = np.asarray(horizons, dtype=np.int64)
        self.terminate_on_success, self.max_step_reward = terminate_on_success, max_step_reward
        n = len(self.horizons)
        self.steps = 0
        self.succeeded = np.zeros(n, dtype=bool)
        self.halted = np.zeros(n, dtype=bool)
        self.terminated = np.zeros(n, dtype=bool)
        self.truncated = np.zeros(n, dtype=bool)

    @property
    def finished(self) -> np.ndarray:
        return self.terminated | self.truncated

    def step(self, reward: np.ndarray, success: np.ndarray, halt: np.ndarray | None = None) -> np.ndarray:
        """Book one step of every episode (reward and success of the episodes still running; the finished ones
        are ignored); `halt`: episodes that end here, terminated, whatever their horizon (MOReL's absorbing state).
        Returns the rewards to hand out: 0 for episodes that had already ended."""
        live = ~self.finished
        self.steps += 1
        success = np.asarray(success, dtype=bool) & live
        reward = np.where(live, reward, 0.0).astype(np.float32)
        self.succeeded |= success
        if self.terminate_on_success:
            reward += np.where(success, self.max_step_reward * (self.horizons - self.steps), 0.0).astype(np.float32)
            self.terminated |= success
        if halt is not None:
            self.halted |= live & ~self.terminated & np.asarray(halt, dtype=bool)
            self.terminated |= self.halted
        self.truncated |= live & ~self.terminated & (self.steps >= self.horizons)
        return reward


class SingleEnv(gym.Env):
    """One episode of a `BatchedEnv` (built with num_envs=1) behind the plain `gym.Env` API, for gymnasium's env
    checker and tools that want a single env. Batch dimensions are dropped."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": CONTROL_FREQ}

    def __init__(self, vector_env: BatchedEnv):
        if vector_env.num_envs != 1:
            raise ValueError(f"SingleEnv wraps a batched env of one episode, got num_envs={vector_env.num_envs}")
        self.vector_env = vector_env
        self.observation_space = vector_env.single_observation_space
        self.action_space = vector_env.single_action_space
        self.render_mode = "rgb_array"

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        obs, info = self.vector_env.reset(seed=seed, options=options)
        return _first(obs), _first(info)

    def step(self, action):
        obs, reward, terminated, truncated, info = self.vector_env.step(np.asarray(action)[None])
        return _first(obs), float(reward[0]), bool(terminated[0]), bool(truncated[0]), _first(info)

    def render(self) -> np.ndarray:
        return self.vector_env.render()[0]


def _first(tree):
    if isinstance(tree, dict):
        return {k: _first(v) for k, v in tree.items()}
    return tree[0] if isinstance(tree, (np.ndarray, list, tuple)) else tree
