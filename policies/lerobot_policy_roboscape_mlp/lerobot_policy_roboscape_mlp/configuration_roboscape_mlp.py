from dataclasses import dataclass, field

from lerobot.configs import NormalizationMode, PreTrainedConfig
from lerobot.configs.types import FeatureType
from lerobot.optim import AdamWConfig


@PreTrainedConfig.register_subclass("roboscape_mlp")
@dataclass
class RoboscapeMLPConfig(PreTrainedConfig):
    """The MLP baseline: a small CNN per camera view, a hashed bag-of-words instruction embedding, an MLP trunk,
    a Gaussian action head (state-independent log-std, as in CleanRL's PPO) and a value head.

    It reads the camera images and the instruction only, never `observation.state`: the world model predicts
    images, so a policy trained in `roboscape_wm` cannot rely on proprioception.

    Args:
        conv_channels: Output channels of the three conv layers of the image encoder (shared by all cameras).
        image_feature_dim: Size of each camera's feature vector.
        instruction_buckets: Hash buckets of the instruction's words (a cheap embedding needing no tokenizer).
        instruction_dim: Size of the instruction embedding.
        hidden_dim: Width of the MLP trunk.
        n_hidden_layers: Depth of the MLP trunk.
        init_log_std: Initial log standard deviation of the Gaussian head, in normalised action units.
        value_hidden_dim: Width of the value head's hidden layer.
        value_grad_scale: Share of the value loss's gradient that reaches the shared encoder and trunk (0: none,
            the critic only reads the features the policy learned; 1: fully shared, as in CleanRL's Agent).
        random_shift_pad: SFT augmentation: each training image is padded by this many pixels (edge replicated)
            and cropped back at a random offset, as DrQ does (0: off).
        chunk_size: Actions predicted per observation: SFT fits the next `chunk_size` demonstrated actions.
        n_action_steps: Actions of each predicted chunk executed before the policy looks again, in evaluation and
            in PPO (which samples them together, one Gaussian over the chunk's first n_action_steps actions).
        binary_gripper: Send the gripper (the last action dimension) fully open or fully closed, never between.
        tokenizer_path: Image trunk: the encoder of this visual tokenizer (`roboscape-train-tokenizer`'s
            pretrained_model, frozen) under a small conv head, instead of the conv stack (None).
        optimizer_lr: Learning rate of the SFT optimiser preset.
        optimizer_weight_decay: Weight decay of the SFT optimiser preset.
    """

    # Inputs and normalisation: images come in [0, 1]; actions are scaled to [-1, 1] with the dataset's range.
    normalization_mapping: dict[str, NormalizationMode] = field(
        default_factory=lambda: {
            "VISUAL": NormalizationMode.IDENTITY,
            "ACTION": NormalizationMode.MIN_MAX,
        }
    )

    # Architecture.
    conv_channels: tuple[int, int, int] = (32, 64, 64)
    image_feature_dim: int = 256
    instruction_buckets: int = 4096
    instruction_dim: int = 64
    hidden_dim: int = 256
    n_hidden_layers: int = 2

    # Action distribution.
    init_log_std: float = -1.5

    # Value head (PPO's critic).
    value_hidden_dim: int = 256
    value_grad_scale: float = 0.0

    # Imitation habits, each measured in docs/results/sft/report.md: the chunk and its open-loop execution are
    # what lift SFT success; the shift and the binary gripper cost nothing.
    random_shift_pad: int = 4
    chunk_size: int = 8
    n_action_steps: int = 4
    binary_gripper: bool = True
    tokenizer_path: str | None = None

    # SFT optimiser preset.
    optimizer_lr: float = 3e-4
    optimizer_weight_decay: float = 1e-4

    def __post_init__(self):
        super().__post_init__()
        if len(self.conv_channels) != 3:
            raise ValueError(f"conv_channels must have 3 entries, got {self.conv_channels!r}")
        if not 1 <= self.n_action_steps <= self.chunk_size:
            raise ValueError(
                f"n_action_steps must be in [1, chunk_size={self.chunk_size}], got {self.n_action_steps!r}"
            )
        if self.random_shift_pad < 0:
            raise ValueError(f"random_shift_pad must be >= 0, got {self.random_shift_pad!r}")
        if not 0 <= self.value_grad_scale <= 1:
            raise ValueError(f"value_grad_scale must be in [0, 1], got {self.value_grad_scale!r}")
        for name in ("image_feature_dim", "instruction_buckets", "instruction_dim", "hidden_dim", "value_hidden_dim"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)!r}")

    def validate_features(self) -> None:
        # Datasets also carry observation.state; this policy ignores it (see the class docstring).
        self.input_features = {
            key: feature for key, feature in self.input_features.items() if feature.type is FeatureType.VISUAL
        }
        if not self.image_features:
            raise ValueError("roboscape_mlp needs at least one camera among its inputs (observation.images.*)")
        shapes = {tuple(feature.shape) for feature in self.image_features.values()}
        if len(shapes) != 1:
            raise ValueError(f"All cameras must have the same image shape, got {self.image_features}")
        if self.action_feature is None:
            raise ValueError("roboscape_mlp needs an `action` output feature")

    def get_optimizer_preset(self) -> AdamWConfig:
        return AdamWConfig(lr=self.optimizer_lr, weight_decay=self.optimizer_weight_decay)

    def get_scheduler_preset(self) -> None:
        return None

    @property
    def observation_delta_indices(self) -> None:
        return None

    @property
    def action_delta_indices(self) -> list[int] | None:
        return list(range(self.chunk_size)) if self.chunk_size > 1 else None

    @property
    def reward_delta_indices(self) -> None:
        return None
