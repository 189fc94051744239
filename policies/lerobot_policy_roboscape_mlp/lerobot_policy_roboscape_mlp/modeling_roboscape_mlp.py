"""The MLP baseline: images + instruction -> Gaussian over the normalised 7-D action, plus a state value.

SFT (`lerobot-train`) fits the Gaussian's mean to the demonstrations; PPO samples from the Gaussian and trains
the whole network, value head included (`lerobot_roboscape.rl.ActorCritic`). The value head reads the trunk's
features through `scale_gradient` (by default it does not train them).
"""

import re
import zlib

import torch
import torch.nn.functional as F
from lerobot.policies.pretrained import PreTrainedPolicy
from lerobot.utils.constants import ACTION, OBS_IMAGES
from torch import Tensor, nn
from torch.distributions import Normal

from lerobot_policy_roboscape_mlp.configuration_roboscape_mlp import RoboscapeMLPConfig
from lerobot_roboscape.actor_critic import ActionEvaluation, PolicySample, scale_gradient


class RoboscapeMLPImageEncoder(nn.Module):
    """Nature-DQN-style conv stack (padded so 32 px views work too), pooled to 4x4 so any image size gives the
    same feature size."""

    def __init__(self, config: RoboscapeMLPConfig):
        super().__init__()
        c1, c2, c3 = config.conv_channels
        self.convs = nn.Sequential(
            nn.Conv2d(3, c1, kernel_size=8, stride=4, padding=2),
            nn.ReLU(),
            nn.Conv2d(c1, c2, kernel_size=4, stride=2, padding=1),
            nn.ReLU(),
            nn.Conv2d(c2, c3, kernel_size=3, stride=1, padding=1),
            nn.ReLU(),
            nn.AdaptiveAvgPool2d(4),
        )
        self.proj = nn.Linear(c3 * 16, config.image_feature_dim)

    def forward(self, images_BCHW: Tensor) -> Tensor:
        return F.relu(self.proj(self.convs(images_BCHW).flatten(1)))


class RoboscapeMLPInstructionEmbedding(nn.Module):
    """Mean of hashed word embeddings: cheap, needs no tokenizer files, and tells the task families apart."""

    def __init__(self, config: RoboscapeMLPConfig):
        super().__init__()
        self.n_buckets = config.instruction_buckets
        self.embedding = nn.EmbeddingBag(config.instruction_buckets, config.instruction_dim, mode="mean")

    def word_ids(self, instruction: str) -> list[int]:
        words = re.findall(r"[a-z0-9]+", instruction.lower()) or [""]
        return [zlib.crc32(word.encode()) % self.n_buckets for word in words]

    def forward(self, instructions: list[str]) -> Tensor:
        ids = [self.word_ids(text) for text in instructions]
        offsets = torch.tensor([0] + [len(i) for i in ids[:-1]]).cumsum(0)
        flat = torch.tensor([i for word_ids in ids for i in word_ids])
        device = self.embedding.weight.device
        return self.embedding(flat.to(device), offsets.to(device))


class RoboscapeMLPPolicy(PreTrainedPolicy):
    config_class = RoboscapeMLPConfig
    name = "roboscape_mlp"

    def __init__(self, config: RoboscapeMLPConfig, **kwargs):
        super().__init__(config)
        config.validate_features()
        self.config = config
        self.camera_keys = sorted(config.image_features)
        self.image_shape = tuple(config.image_features[self.camera_keys[0]].shape)
        action_dim = config.action_feature.shape[0]

        self.image_encoder = RoboscapeMLPImageEncoder(config)
        self.instruction_embedding = RoboscapeMLPInstructionEmbedding(config)
        layers, width = [], len(self.camera_keys) * config.image_feature_dim + config.instruction_dim
        for _ in range(config.n_hidden_layers):
            layers += [nn.Linear(width, config.hidden_dim), nn.Tanh()]
            width = config.hidden_dim
        self.trunk = nn.Sequential(*layers)
        self.action_mean = nn.Linear(width, action_dim)
        self.action_log_std = nn.Parameter(torch.full((action_dim,), config.init_log_std))
        self.value_head = nn.Sequential(
            nn.Linear(width, config.value_hidden_dim), nn.Tanh(), nn.Linear(config.value_hidden_dim, 1)
        )

    # LeRobot's policy API.

    def get_optim_params(self) -> dict:
        return self.parameters()

    def reset(self):
        pass  # no observation history, no action queue

    def forward(self, batch: dict[str, Tensor]) -> tuple[Tensor, dict]:
        """SFT loss: mean squared error of the Gaussian's mean against the normalised demonstration action."""
        mean = self.action_mean(self.features(batch))
        loss = F.mse_loss(mean, batch[ACTION])
        return loss, {"mse": loss.item()}

    @torch.no_grad()
    def predict_action_chunk(self, batch: dict[str, Tensor], **kwargs) -> Tensor:
        return self.select_action(batch).unsqueeze(1)  # (B, 1, action_dim)

    @torch.no_grad()
    def select_action(self, batch: dict[str, Tensor], **kwargs) -> Tensor:
        """The Gaussian's mean (B, action_dim): deterministic, for evaluation."""
        return self.action_mean(self.features(batch)).clamp(-1, 1)

    # What PPO needs (lerobot_roboscape.rl.ActorCritic).

    def sample_action(self, batch: dict) -> PolicySample:
        features = self.features(batch)
        distribution = self.distribution(features)
        action = distribution.sample()
        log_prob = distribution.log_prob(action).sum(-1)
        # [-1, 1] is the demonstrations' action range under MIN_MAX normalisation: the env gets the sample clipped
        # to it, PPO scores the unclipped one (as CleanRL).
        return PolicySample(action.clamp(-1, 1), action, log_prob, self.value(features))

    def evaluate_actions(self, batch: dict, raw_action: Tensor) -> ActionEvaluation:
        features = self.features(batch)
        distribution = self.distribution(features)
        return ActionEvaluation(
            log_prob=distribution.log_prob(raw_action).sum(-1),
            entropy=distribution.entropy().sum(-1),
            value=self.value(features),
        )

    def predict_value(self, batch: dict) -> Tensor:
        return self.value(self.features(batch))

    # Internals.

    def value(self, features: Tensor) -> Tensor:
        return self.value_head(scale_gradient(features, self.config.value_grad_scale)).squeeze(-1)

    def distribution(self, features: Tensor) -> Normal:
        mean = self.action_mean(features)
        return Normal(mean, self.action_log_std.exp().expand_as(mean))

    def features(self, batch: dict) -> Tensor:
        images = [self.camera(batch, key) for key in self.camera_keys]
        n_cameras, batch_size = len(images), images[0].shape[0]
        image_features = self.image_encoder(torch.cat(images))  # (n_cameras * B, F)
        image_features = image_features.view(n_cameras, batch_size, -1).transpose(0, 1).flatten(1)
        instruction = self.instruction_embedding(self.instructions(batch, batch_size))
        return self.trunk(torch.cat([image_features, instruction], dim=-1))

    def camera(self, batch: dict, key: str) -> Tensor:
        if key not in batch:
            cameras = sorted(k for k in batch if k.startswith(f"{OBS_IMAGES}."))
            raise KeyError(f"roboscape_mlp expects camera {key!r}; the batch has {cameras}")
        images = batch[key]
        if tuple(images.shape[1:]) != self.image_shape:
            raise ValueError(
                f"{key} has images of shape {tuple(images.shape[1:])}, but this policy was built for "
                f"{self.image_shape} (C, H, W)"
            )
        return images

    @staticmethod
    def instructions(batch: dict, batch_size: int) -> list[str]:
        task = batch.get("task")
        if task is None:
            raise KeyError("roboscape_mlp needs the instruction under the batch key 'task'")
        tasks = [task] * batch_size if isinstance(task, str) else list(task)
        if len(tasks) != batch_size:
            raise ValueError(f"Got {len(tasks)} instructions for a batch of {batch_size} observations")
        return tasks
