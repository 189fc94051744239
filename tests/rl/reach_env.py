"""A tiny env where PPO's improvement is certain: every step pays 1 - mean|action - 0.5|, the image is a fixed
grey frame, the instruction is fixed. Registered as the LeRobot env type `ppo_test_reach`."""

from dataclasses import dataclass

import gymnasium as gym
import numpy as np
from lerobot.envs.configs import EnvConfig

from lerobot_roboscape.envs.batched import BatchedEnv
from lerobot_roboscape.envs.configs import camera_features

TARGET = 0.5


class ReachEnv(BatchedEnv):
    def __init__(self, image_size: int, episode_length: int, num_envs: int):
        self.num_envs, self._max_episode_steps, self.image_size = num_envs, episode_length, image_size
        image = gym.spaces.Box(0, 255, (num_envs, image_size, image_size, 3), np.uint8)
        self.observation_space = gym.spaces.Dict({"pixels": gym.spaces.Dict({"third_view": image})})
        self.action_space = gym.spaces.Box(-1, 1, (num_envs, 7), np.float32)
        self.single_action_space = gym.spaces.Box(-1, 1, (7,), np.float32)
        self.t = 0

    def tasks(self):
        return ("reach the target",) * self.num_envs

    def _observation(self):
        return {"pixels": {"third_view": np.full((self.num_envs, self.image_size, self.image_size, 3), 128, np.uint8)}}

    def reset(self, *, seed=None, options=None):
        self.t = 0
        return self._observation(), {"task": self.tasks()}

    def step(self, actions):
        actions, clipped = self._check_actions(actions)
        self.t += 1
        reward = 1.0 - np.abs(actions - TARGET).mean(axis=1)
        terminated = np.zeros(self.num_envs, dtype=bool)
        truncated = np.full(self.num_envs, self.t >= self._max_episode_steps)
        return self._observation(), reward, terminated, truncated, {"is_success": reward > 0.95}

    def render(self):
        return list(self._observation()["pixels"]["third_view"])


@EnvConfig.register_subclass("ppo_test_reach")
@dataclass
class ReachEnvConfig(EnvConfig):
    image_size: int = 32
    episode_length: int = 4
    task: str = "reach"
    fps: int = 20

    def __post_init__(self):
        self.features, self.features_map = camera_features(self.image_size, ("third_view",))

    @property
    def gym_kwargs(self) -> dict:
        return {}

    def create_envs(self, n_envs: int, use_async_envs: bool = False):
        return {self.type: {0: ReachEnv(self.image_size, self.episode_length, n_envs)}}
