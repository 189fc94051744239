"""The MLP baseline: images + instruction -> Gaussian over the normalised 7-D action, plus a state value.

SFT (`lerobot-train`) fits the Gaussian's mean to the demonstrations, optionally a chunk of the next actions on
randomly shifted images; PPO samples from the Gaussian over the chunk's first `n_action_steps` actions (the
ones evaluation executes before looking again), executes them in order, and trains the whole network, value head
included (`lerobot_roboscape.rl.ActorCritic`). The value head reads the trunk's features
through `scale_gradient` (by default it does not train them).
"""

import re
import zlib
from collections import deque

import torch
import torch.nn.functional as F
from lerobot.policies.pretrained import PreTrainedPolicy
from lerobot.utils.constants import ACTION, OBS_IMAGES
from torch import Tensor, nn
from torch.distributions import Normal

from lerobot_policy_roboscape_mlp.configuration_roboscape_mlp import RoboscapeMLPConfig
from roboscape_core.actor_critic import ActionEvaluation, PolicySample, scale_gradient
from roboscape_core.errors import MissingInputError


def random_shift(images_BCHW: Tensor, pad: int) -> Tensor:
    """Each image translated by up to `pad` pixels in x and y, its edge repeated into the gap (DrQ's augmentation)."""
    b, _, h, w = images_BCHW.shape
    padded = F.pad(images_BCHW, (pad, pad, pad, pad), mode="replicate")
    dy, dx = torch.randint(0, 2 * pad + 1, (2, b)).tolist()
    return torch.stack([padded[i, :, y : y + h, x : x + w] for i, (y, x) in enumerate(zip(dy, dx, strict=True))])


def binarize_gripper(actions: Tensor) -> Tensor:
    """The gripper (last dimension, normalised to [-1, 1]) set fully closed (-1) or fully open (1)."""
    gripper = torch.where(actions[..., -1:] >= 0, 1.0, -1.0)
    return torch.cat([actions[..., :-1], gripper], dim=-1)


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


class RoboscapeMLPTokenizerTrunk(nn.Module):
    """The visual tokenizer's encoder (frozen: the world model's view of the scene) under a small trainable conv
    head. Its continuous latents, before quantisation, carry the most of what it saw."""

    def __init__(self, config: RoboscapeMLPConfig):
        super().__init__()
        try:  # the one trunk that needs the pipeline: the plugin installs without it
            from lerobot_roboscape.tokenizer.modeling_tokenizer import VisualTokenizer, encoder_input
        except ModuleNotFoundError as error:
            raise MissingInputError(
                f"roboscape_mlp's tokenizer_path={config.tokenizer_path!r} reads a visual tokenizer, which lives in "
                "lerobot-roboscape: install it, or leave tokenizer_path unset for the conv trunk"
            ) from error

        self.encoder_input = encoder_input

        self.encoder = VisualTokenizer.from_pretrained(config.tokenizer_path).encoder.requires_grad_(False)
        c1, c2, _ = config.conv_channels
        bits = self.encoder.layers[-1].out_channels
        self.head = nn.Sequential(
            nn.Conv2d(bits, c1, kernel_size=3, padding=1),
            nn.ReLU(),
            nn.Conv2d(c1, c2, kernel_size=3, stride=2, padding=1),
            nn.ReLU(),
            nn.AdaptiveAvgPool2d(4),
        )
        self.proj = nn.Linear(c2 * 16, config.image_feature_dim)

    def forward(self, images_BCHW: Tensor) -> Tensor:
        with torch.no_grad():
            latents = self.encoder.eval()(self.encoder_input(images_BCHW))
        return F.relu(self.proj(self.head(latents).flatten(1)))


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
        self.action_dim = action_dim = config.action_feature.shape[0]

        trunk = RoboscapeMLPTokenizerTrunk if config.tokenizer_path else RoboscapeMLPImageEncoder
        self.image_encoder = trunk(config)
        self.instruction_embedding = RoboscapeMLPInstructionEmbedding(config)
        layers, width = [], len(self.camera_keys) * config.image_feature_dim + config.instruction_dim
        for _ in range(config.n_hidden_layers):
            layers += [nn.Linear(width, config.hidden_dim), nn.Tanh()]
            width = config.hidden_dim
        self.trunk = nn.Sequential(*layers)
        self.action_mean = nn.Linear(width, config.chunk_size * action_dim)  # the chunk's actions, in order
        self.action_log_std = nn.Parameter(torch.full((action_dim,), config.init_log_std))
        self.value_head = nn.Sequential(
            nn.Linear(width, config.value_hidden_dim), nn.Tanh(), nn.Linear(config.value_hidden_dim, 1)
        )

    # LeRobot's policy API.

    def get_optim_params(self) -> dict:
        return self.parameters()

    def reset(self):
        self._action_queue = deque(maxlen=self.config.n_action_steps)

    def forward(self, batch: dict[str, Tensor]) -> tuple[Tensor, dict]:
        """SFT loss: mean squared error of the predicted chunk against the normalised demonstrated actions, the
        steps past an episode's end left out."""
        if self.config.random_shift_pad:
            batch = {
                **batch,
                **{key: random_shift(batch[key], self.config.random_shift_pad) for key in self.camera_keys},
            }
        chunk = self.chunk(self.features(batch))
        target = batch[ACTION].view_as(chunk)
        error = F.mse_loss(chunk, target, reduction="none").mean(-1)  # (B, chunk_size)
        keep = ~batch["action_is_pad"] if "action_is_pad" in batch else torch.ones_like(error, dtype=torch.bool)
        loss = error[keep].mean()
        return loss, {"mse": loss.item(), "mse_first": error[:, 0].mean().item()}

    @torch.no_grad()
    def predict_action_chunk(self, batch: dict[str, Tensor], **kwargs) -> Tensor:
        """The predicted chunk's means (B, chunk_size, action_dim), for evaluation."""
        chunk = self.chunk(self.features(batch)).clamp(-1, 1)
        return binarize_gripper(chunk) if self.config.binary_gripper else chunk

    @torch.no_grad()
    def select_action(self, batch: dict[str, Tensor], **kwargs) -> Tensor:
        """The next action (B, action_dim): deterministic, for evaluation. A new chunk is predicted every
        `n_action_steps` steps (every step by default); `reset()` between episodes."""
        if not getattr(self, "_action_queue", None):
            self.reset()
            chunk = self.predict_action_chunk(batch)[:, : self.config.n_action_steps]
            self._action_queue.extend(chunk.transpose(0, 1))
        return self._action_queue.popleft()

    # What PPO needs (lerobot_roboscape.rl.ActorCritic).

    def sample_action(self, batch: dict) -> PolicySample:
        features = self.features(batch)
        distribution = self.distribution(features)
        action = distribution.sample()
        log_prob = distribution.log_prob(action).sum((-2, -1))
        # [-1, 1] is the demonstrations' action range under MIN_MAX normalisation: the env gets the sample clipped
        # to it, PPO scores the unclipped one (as CleanRL).
        env_action = action.clamp(-1, 1)
        if self.config.binary_gripper:
            env_action = binarize_gripper(env_action)
        return PolicySample(env_action, action, log_prob, self.value(features))

    def evaluate_actions(self, batch: dict, raw_action: Tensor) -> ActionEvaluation:
        features = self.features(batch)
        distribution = self.distribution(features)
        return ActionEvaluation(
            log_prob=distribution.log_prob(raw_action).sum((-2, -1)),
            entropy=distribution.entropy().sum((-2, -1)),
            value=self.value(features),
        )

    def predict_value(self, batch: dict) -> Tensor:
        return self.value(self.features(batch))

    @torch.no_grad()
    def set_action_std(self, std: float) -> None:
        """The Gaussian's std on every action dimension (PPO's `init_std`: SFT trains only its mean)."""
        self.action_log_std.fill_(float(torch.tensor(std).log()))

    # Internals.

    def value(self, features: Tensor) -> Tensor:
        return self.value_head(scale_gradient(features, self.config.value_grad_scale)).squeeze(-1)

    def chunk(self, features: Tensor) -> Tensor:
        return self.action_mean(features).view(len(features), self.config.chunk_size, self.action_dim)

    def distribution(self, features: Tensor) -> Normal:
        """PPO's Gaussian over the actions executed before the policy looks again (B, n_action_steps, action_dim):
        the chunk's first `n_action_steps`, as evaluation executes them (the rest only shaped the features in SFT)."""
        mean = self.chunk(features)[:, : self.config.n_action_steps]
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
