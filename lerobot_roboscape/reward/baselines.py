"""Learned rewards read from frames: the paper's baselines (section 4.1) and a success classifier.

- Embedding-based (iVideoGPT): an MLP head on the action world model's hidden state of the current frame, fitted
  to the rule-based reward labels.
- Proxy-based (DiWA): a separate network from the current images to the rule-based reward.
- Success (DIAMOND's termination head, RLinf's reward classifier): the proxy's network from the current images to
  the logit of "the task is accomplished in this frame", fitted to the done labels with a balanced loss. It is an
  alternative to the action world model's done head (`--env.done_source=classifier`).
All are trained by `roboscape-train-reward`; `roboscape_wm` uses the first two with `--env.reward_type`.
"""

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from lerobot_roboscape.io.weights import CheckedHubMixin
from lerobot_roboscape.training.losses import balanced_bce
from roboscape_core.errors import InvalidInputError

REWARD_KINDS = ("embedding", "proxy", "success")
IMAGE_KINDS = ("proxy", "success")  # read decoded images; the embedding reads world-model features


@dataclass
class RewardModelConfig:
    """Args:
    kind: "embedding" (head on the world model's hidden state), "proxy" (image network) or "success" (image
        network giving the logit of success).
    d_model: width of the world model's hidden state (embedding; taken from the world model).
    image_size: camera image side (proxy; taken from the tokenizer).
    n_cameras: views per frame (proxy).
    channels: base width of the proxy's conv encoder.
    hidden: hidden width of the MLP.
    """

    kind: str = "embedding"
    d_model: int = 128
    image_size: int = 64
    n_cameras: int = 2
    channels: int = 16
    hidden: int = 256

    def __post_init__(self):
        if self.kind not in REWARD_KINDS:
            raise InvalidInputError(f"kind must be one of {REWARD_KINDS}, got {self.kind!r}")


class RewardModel(
    nn.Module, CheckedHubMixin, library_name="lerobot-roboscape", tags=["lerobot", "reward-model", "robotics"]
):
    """Predicts the rule-based reward of a frame (embedding, proxy) or the logit of its success (success), from
    world-model features (B, d_model) or images (B, n_cameras, 3, H, W) in [0, 1], depending on `config.kind`."""

    def __init__(self, config: RewardModelConfig):
        super().__init__()
        self.config = config
        if config.kind == "embedding":
            width = config.d_model
            # Token-averaged hidden states share a large common part and differ little between frames;
            # standardising each feature over the data (batch statistics) exposes the differences.
            self.encoder = nn.BatchNorm1d(config.d_model)
        else:  # proxy and success
            c = config.channels
            self.encoder = nn.Sequential(  # shared over views; the views' features are concatenated
                nn.Conv2d(3, c, 4, 2, 1),
                nn.SiLU(),
                nn.Conv2d(c, 2 * c, 4, 2, 1),
                nn.SiLU(),
                nn.Conv2d(2 * c, 4 * c, 4, 2, 1),
                nn.SiLU(),
                nn.AdaptiveAvgPool2d(1),
                nn.Flatten(),
            )
            width = 4 * c * config.n_cameras
        self.head = nn.Sequential(nn.Linear(width, config.hidden), nn.SiLU(), nn.Linear(config.hidden, 1))

    def forward(self, inputs: torch.Tensor) -> torch.Tensor:
        if self.config.kind in IMAGE_KINDS:
            B, n = inputs.shape[:2]
            if n != self.config.n_cameras or inputs.shape[-1] != self.config.image_size:
                raise ValueError(
                    f"proxy reward expects (B, {self.config.n_cameras}, 3, {self.config.image_size}, "
                    f"{self.config.image_size}) images, got {tuple(inputs.shape)}"
                )
            return self.head(self.encoder(inputs.flatten(0, 1) * 2 - 1).reshape(B, -1)).squeeze(-1)
        return self.head(self.encoder(inputs)).squeeze(-1)

    @torch.no_grad()
    def success_probability(self, images: torch.Tensor) -> torch.Tensor:
        """(B, n_cameras, 3, H, W) in [0, 1] -> (B,) probability that the task is accomplished (kind success)."""
        return torch.sigmoid(self(images).float())

    def compute_loss(self, inputs: torch.Tensor, labels: torch.Tensor) -> tuple[torch.Tensor, dict]:
        """labels: the rule-based reward, or the done labels for the success kind."""
        fit = balanced_bce if self.config.kind == "success" else F.mse_loss
        loss = fit(self(inputs), labels)
        return loss, {"loss": loss.item()}
