"""The world-model reward of RoboScape-R (paper Eq. 5-8): a sparse term from the action model's done signal and a
dense term from the LPIPS distance between the current frame and the goal frame.

    reward = alpha * sparse + beta * dense
    sparse = sparse_value if done >= theta_sps else 0
    dense  = 1 - LPIPS(frame, goal), averaged over the camera views

LPIPS is a distance (0 for identical images), so 1 - LPIPS grows as the frame approaches the goal.
"""

from dataclasses import dataclass

import torch
from torch import nn


@dataclass
class RewardParts:
    reward: torch.Tensor  # (B,)
    sparse: torch.Tensor  # (B,) 0 or sparse_value
    dense: torch.Tensor  # (B,) 1 - LPIPS
    lpips: torch.Tensor  # (B,)


class WorldModelReward(nn.Module):
    def __init__(self, lpips_metric: nn.Module, alpha: float = 0.5, beta: float = 0.5, theta_sps: float = 0.9,
                 sparse_value: float = 10.0):
        super().__init__()
        self.lpips = lpips_metric
        self.alpha, self.beta, self.theta_sps, self.sparse_value = alpha, beta, theta_sps, sparse_value

    @torch.no_grad()
    def forward(self, frames: torch.Tensor, goals: torch.Tensor, done: torch.Tensor) -> RewardParts:
        """frames, goals: (B, n_cameras, 3, H, W) in [0, 1]; done: (B,) done probability of the action model."""
        B, n = frames.shape[:2]
        distance = self.lpips(frames.flatten(0, 1) * 2 - 1, goals.flatten(0, 1) * 2 - 1).reshape(B, n).mean(1)
        dense = 1 - distance
        sparse = (done >= self.theta_sps).float() * self.sparse_value
        return RewardParts(self.alpha * sparse + self.beta * dense, sparse, dense, distance)
