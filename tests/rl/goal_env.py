"""A tiny env with the paper's reward shape, where success must be learnt: a point on a line starts at -0.5 and must
reach the goal at +0.5 (within 0.1); `start` moves the start nearer. The shaping reward 1 - |x - goal| / 2 is
positive everywhere; the sparse reward is paid at every step spent at the goal. The image's grey level shows the
position. Episodes follow `EpisodeBook` (fixed horizon by default, or termination with its bonus). Registered as
`ppo_test_goal`."""

from dataclasses import dataclass

import gymnasium as gym
import numpy as np
from lerobot.envs.configs import EnvConfig

from lerobot_roboscape.envs.batched import BatchedEnv, EpisodeBook, start_groups
from lerobot_roboscape.reward.world_model_reward import max_step_reward
from tests.rl.reach_env import ReachEnvConfig

START, GOAL, TOLERANCE, SPEED = -0.5, 0.5, 0.1, 0.25


class GoalEnv(BatchedEnv):
    def __init__(self, config: "GoalEnvConfig", num_envs: int):
        self.config, self.num_envs, self._max_episode_steps = config, num_envs, config.episode_length
        size = config.image_size
        self.observation_space = gym.spaces.Dict(
            {"pixels": gym.spaces.Dict({"third_view": gym.spaces.Box(0, 255, (num_envs, size, size, 3), np.uint8)})}
        )
        self.action_space = gym.spaces.Box(-1, 1, (num_envs, 7), np.float32)
        self.single_action_space = gym.spaces.Box(-1, 1, (7,), np.float32)
        self.position = np.full(num_envs, config.start)

    def tasks(self):
        return ("move to the goal",) * self.num_envs

    def _observation(self):
        grey = np.round((self.position + 1) * 127.5).astype(np.uint8)
        size = self.config.image_size
        return {"pixels": {"third_view": np.repeat(grey[:, None, None, None], size, 1).repeat(size, 2).repeat(3, 3)}}

    def reset(self, *, seed=None, options=None):
        self.position = np.full(self.num_envs, self.config.start)
        groups = start_groups([""] * self.num_envs, int((options or {}).get("group_size", 1)))
        cfg = self.config
        self.book = EpisodeBook(
            np.full(self.num_envs, cfg.episode_length),
            cfg.terminate_on_success,
            max_step_reward(cfg.alpha, cfg.beta, cfg.sparse_reward),
        )
        return self._observation(), {"task": self.tasks(), "group": groups}

    def step(self, actions):
        actions, _ = self._check_actions(actions)
        live = ~self.book.finished
        self.position = np.where(live, np.clip(self.position + SPEED * actions[:, 0], -1, 1), self.position)
        at_goal = np.abs(self.position - GOAL) < TOLERANCE
        cfg = self.config
        reward = cfg.alpha * cfg.sparse_reward * at_goal + cfg.beta * (1 - np.abs(self.position - GOAL) / 2)
        reward = self.book.step(reward, at_goal)
        info = {"is_success": self.book.succeeded.copy()}
        return self._observation(), reward, self.book.terminated.copy(), self.book.truncated.copy(), info

    def render(self):
        return list(self._observation()["pixels"]["third_view"])


@EnvConfig.register_subclass("ppo_test_goal")
@dataclass
class GoalEnvConfig(ReachEnvConfig):
    episode_length: int = 8
    terminate_on_success: bool = False
    alpha: float = 0.5
    beta: float = 0.5
    sparse_reward: float = 10.0
    task: str = "goal"
    start: float = START

    def create_envs(self, n_envs: int, use_async_envs: bool = False):
        return {self.type: {0: GoalEnv(self, n_envs)}}
