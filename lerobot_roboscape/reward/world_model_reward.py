"""The world-model reward of RoboScape-R (paper Eq. 5-8, Algorithm 1): a sparse term from the action model's done
signal and a dense term from the perceptual distance between the current frame and the goal frame.

    reward = alpha * sparse + beta * dense
    sparse = sparse_value if done >= theta_sps else 0
    dense  = 1 - distance(frame, goal), averaged over the camera views

`distance` is LPIPS (the paper's metric) or the tokenizer-feature distance (no download needed), see
`lerobot_roboscape.tokenizer.similarity.load_similarity`. Both are 0 for identical images, so 1 - distance grows as the
frame approaches the goal, and 1 is the most a step's dense term can pay.
"""

from dataclasses import dataclass

import torch
from torch import nn

from lerobot_roboscape.tokenizer.similarity import frame_distance


def max_step_reward(alpha: float, beta: float, sparse_value: float) -> float:
    """The most one step can pay: the sparse term on, and the dense term at its maximum of 1."""
    return alpha * sparse_value + beta * 1.0


@dataclass
class RewardParts:
    reward: torch.Tensor  # (B,)
    sparse: torch.Tensor  # (B,) 0 or sparse_value
    dense: torch.Tensor  # (B,) 1 - distance
    distance: torch.Tensor  # (B,) perceptual distance to the goal


class WorldModelReward(nn.Module):
    def __init__(
        self,
        distance: nn.Module,
        alpha: float = 0.5,
        beta: float = 0.5,
        theta_sps: float = 0.9,
        sparse_value: float = 10.0,
    ):
        super().__init__()
        self.distance = distance
        self.alpha, self.beta, self.theta_sps, self.sparse_value = alpha, beta, theta_sps, sparse_value

    @property
    def max_step_reward(self) -> float:
        return max_step_reward(self.alpha, self.beta, self.sparse_value)

    @torch.no_grad()
    def forward(self, frames: torch.Tensor, goals: torch.Tensor, done: torch.Tensor) -> RewardParts:
        """frames, goals: (B, n_cameras, 3, H, W) in [0, 1]; done: (B,) done probability of the action model."""
        distance = frame_distance(self.distance, frames, goals)
        dense = 1 - distance
        sparse = (done >= self.theta_sps).float() * self.sparse_value
        return RewardParts(self.alpha * sparse + self.beta * dense, sparse, dense, distance)
