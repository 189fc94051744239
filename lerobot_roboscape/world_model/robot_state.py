"""The robot's state as a channel of the world model: read into every position of its frame, and predicted for the
next frame.

A frame's state (`observation.state`: joint positions and the TCP pose), normalised by the training data's
statistics (saved in the model's config, as the actions' are), is embedded and added to each of the frame's
positions. The next frame's state is predicted from this frame's state, the frame's pooled hidden state and the next
frame's pooled control (its k actions, or the instruction): a residual in normalised units, zero at initialisation,
so an untrained head predicts that the arm stays where it is. Every caller passes and receives raw states.
"""

import torch
import torch.nn.functional as F
from torch import nn

from lerobot_roboscape.robot import STATE_DIM, TCP_QUATERNION
from lerobot_roboscape.world_model.configuration_world_model import WorldModelConfig

# Statistics that leave the robot's states as they are: models built without data (benchmarks, tests).
UNIT_STATE_STATS = {"state_dim": STATE_DIM, "state_mean": [0.0] * STATE_DIM, "state_std": [1.0] * STATE_DIM}
# Some dimensions barely move in the data (the TCP's quaternion while the gripper points down): without a floor, a
# policy's small rotation would read as hundreds of std.
STATE_STD_FLOOR = 0.01


class RobotState(nn.Module):
    def __init__(self, config: WorldModelConfig):
        super().__init__()
        D, C = config.state_dim, config.d_model
        mean = torch.zeros(D) if config.state_mean is None else torch.tensor(config.state_mean)
        std = torch.ones(D) if config.state_std is None else torch.tensor(config.state_std)
        self.register_buffer("mean", mean.float(), persistent=False)
        self.register_buffer("std", std.float().clamp(min=STATE_STD_FLOOR), persistent=False)
        self.has_quaternion = D == STATE_DIM  # the robot's layout; a synthetic world's 2-D cell has none
        self.embed = nn.Sequential(nn.Linear(D, C), nn.GELU(), nn.Linear(C, C))
        self.head = nn.Sequential(nn.Linear(2 * C + D, config.done_hidden), nn.GELU(), nn.Linear(config.done_hidden, D))

    def zero_init_head(self) -> None:
        """The head starts by predicting no motion (called after the model's normal initialisation)."""
        nn.init.zeros_(self.head[-1].weight)
        nn.init.zeros_(self.head[-1].bias)

    def normalise(self, state: torch.Tensor) -> torch.Tensor:
        if self.has_quaternion:
            state = same_hemisphere(state, self.mean[TCP_QUATERNION])
        return (state - self.mean.to(state.dtype)) / self.std.to(state.dtype)

    def embedding(self, state_BTD: torch.Tensor) -> torch.Tensor:
        """(B, T, D) raw states -> (B, T, C), added to every position of their frames."""
        return self.embed(self.normalise(state_BTD.float()))

    def _delta(self, features: torch.Tensor, normalised: torch.Tensor, pooled: torch.Tensor) -> torch.Tensor:
        return self.head(torch.cat([features.float(), normalised, pooled.float()], -1))

    def predict_next(self, features_BC: torch.Tensor, state_BD: torch.Tensor, pooled_BC: torch.Tensor) -> torch.Tensor:
        """The next frame's raw state (B, D) from this frame's features (B, C) and raw state, and the next frame's
        pooled control (B, C)."""
        normalised = self.normalise(state_BD.float())
        following = normalised + self._delta(features_BC, normalised, pooled_BC)
        return following * self.std + self.mean

    def loss(self, features_BTC: torch.Tensor, state_BTD: torch.Tensor, pooled_BTC: torch.Tensor) -> torch.Tensor:
        """Mean squared error, in normalised units, of each frame's predicted next state against the clip's next
        frame. pooled: (B, T, C) per frame (actions) or (B, 1, C) shared (text)."""
        normalised = self.normalise(state_BTD.float())
        pooled = pooled_BTC[:, 1:] if pooled_BTC.shape[1] > 1 else pooled_BTC.expand(-1, normalised.shape[1] - 1, -1)
        predicted = normalised[:, :-1] + self._delta(features_BTC[:, :-1], normalised[:, :-1], pooled)
        return F.mse_loss(predicted, normalised[:, 1:])


def same_hemisphere(state: torch.Tensor, reference: torch.Tensor) -> torch.Tensor:
    """The state with its TCP quaternion's sign on the reference's side. q and -q are one orientation, and the
    simulator reports either: 24 frames of the bench's exploration jump from one to the other, 56 std apart in
    normalised units, and the batches that held one multiplied the state's loss by a thousand."""
    q = state[..., TCP_QUATERNION]
    sign = torch.where((q * reference).sum(-1, keepdim=True) < 0, -1.0, 1.0)
    return torch.cat([state[..., : TCP_QUATERNION.start], q * sign, state[..., TCP_QUATERNION.stop :]], -1)
