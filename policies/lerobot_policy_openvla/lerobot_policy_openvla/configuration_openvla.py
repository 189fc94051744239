from dataclasses import dataclass, field

from lerobot.configs import NormalizationMode, PreTrainedConfig
from lerobot.configs.types import FeatureType
from lerobot.optim import AdamWConfig

OPENVLA_7B = "openvla/openvla-7b"


@PreTrainedConfig.register_subclass("openvla")
@dataclass
class OpenVLAConfig(PreTrainedConfig):
    """OpenVLA-7B fine-tuned with LoRA, plus RL4VLA's value head for PPO.

    Checkpoints of this policy hold only the LoRA adapter and the value head; `base_model` names the OpenVLA
    checkpoint they apply to, which is loaded again (from the Hub cache or a local directory) at load time.

    Args:
        base_model: The OpenVLA checkpoint: a Hub repo id or a local directory in the published layout of
            `openvla/openvla-7b` (the paper preset), or a random preset of the same architecture: "tiny" (toy
            sizes, for CPU runs, tests and the demo) or "random-7b" (the published sizes, to measure memory and
            speed without downloading). Random presets draw the same weights for a given `init_seed`.
        base_revision: Hub revision of `base_model`.
        init_seed: Seed of a random preset's weights.
        camera: The image feature the model sees (OpenVLA reads one third-person image); default: the third
            view if the dataset has one, else the first camera.
        unnorm_key: The dataset of the base checkpoint's `norm_stats` whose action statistics (q01, q99, mask)
            normalise and un-normalise actions, as `predict_action(unnorm_key=...)` (e.g. "bridge_orig" to run
            openvla/openvla-7b zero-shot). None: the training dataset's statistics (gripper masked, as OpenVLA's
            fine-tuning), or, without a dataset, the base checkpoint's only dataset.
        lora_r: LoRA rank.
        lora_alpha: LoRA scaling numerator (scale = alpha / r).
        lora_dropout: Dropout on the LoRA branch.
        lora_target_modules: ["all-linear"] (every linear layer of the vision towers, projector and LLM, except
            the LM head, as peft's "all-linear" in OpenVLA's finetune.py) or module-name suffixes understood by
            peft (e.g. ["q_proj", "v_proj"]). The LM head stays frozen by default: one adapter serves SFT and then
            PPO here, and OpenVLA's SFT recipe leaves the head out. RL4VLA's PPO adapter (a fresh one on the
            merged SFT weights) also targets it; its list is ["proj", "qkv", "fc1", "fc2", "q", "kv", "fc3",
            "q_proj", "k_proj", "v_proj", "o_proj", "gate_proj", "up_proj", "down_proj", "lm_head"]. Adapters
            start as OpenVLA's and RL4VLA's (init_lora_weights="gaussian": A ~ N(0, 1/r^2), B = 0).
        dtype: Weights of the frozen base: "bfloat16", "float32", or "auto" (bfloat16 on GPUs that support it).
        gradient_checkpointing: Recompute activations in the backward pass (needed at 7B scale).
        value_head_dims: Hidden sizes of the value MLP on the last prompt token's hidden state.
        value_grad_scale: Share of the value loss's gradient that reaches the LoRA adapter through that hidden
            state (1: RL4VLA's shared trunk; 0: the critic reads the features without training them).
        temperature: Softmax temperature of PPO's action sampling (and of its log-probs).
        optimizer_lr: Learning rate of the SFT optimiser preset.
    """

    # Inputs and normalisation: images in [0, 1]; actions scaled to [-1, 1] with q01/q99 except the masked
    # (gripper) dimension, as OpenVLA does before binning, by the processors' own steps (processor_openvla.py),
    # so LeRobot's normaliser leaves the action alone.
    normalization_mapping: dict[str, NormalizationMode] = field(
        default_factory=lambda: {
            "VISUAL": NormalizationMode.IDENTITY,
            "ACTION": NormalizationMode.IDENTITY,
        }
    )
    camera: str | None = None
    unnorm_key: str | None = None

    # Base model.
    base_model: str = OPENVLA_7B
    base_revision: str | None = None
    init_seed: int = 0

    # LoRA (OpenVLA's fine-tuning recipe).
    lora_r: int = 32
    lora_alpha: int = 16
    lora_dropout: float = 0.0
    lora_target_modules: list[str] = field(default_factory=lambda: ["all-linear"])

    # Compute.
    dtype: str = "auto"
    gradient_checkpointing: bool = True

    # RL (RL4VLA).
    value_head_dims: tuple[int, ...] = (512, 128)
    value_grad_scale: float = 1.0
    temperature: float = 1.0

    # SFT optimiser preset.
    optimizer_lr: float = 5e-4
    optimizer_weight_decay: float = 0.0

    def __post_init__(self):
        super().__post_init__()
        if self.dtype not in ("auto", "bfloat16", "float32"):
            raise ValueError(f"dtype must be 'auto', 'bfloat16' or 'float32', got {self.dtype!r}")
        if self.lora_r < 1:
            raise ValueError(f"lora_r must be positive, got {self.lora_r!r}")
        if self.temperature <= 0:
            raise ValueError(f"temperature must be positive, got {self.temperature!r}")
        if not 0 <= self.value_grad_scale <= 1:
            raise ValueError(f"value_grad_scale must be in [0, 1], got {self.value_grad_scale!r}")

    def validate_features(self) -> None:
        cameras = sorted(key for key, ft in self.input_features.items() if ft.type is FeatureType.VISUAL)
        if not cameras:
            raise ValueError("openvla needs a camera among its inputs (observation.images.*)")
        if self.camera is None:
            third_view = [key for key in cameras if key.endswith("third_view")]
            self.camera = (third_view or cameras)[0]
        if self.camera not in cameras:
            raise ValueError(f"camera={self.camera!r} is not among the input cameras {cameras}")
        self.input_features = {self.camera: self.input_features[self.camera]}  # one image, no proprioception
        if self.action_feature is None or self.action_feature.shape != (7,):
            raise ValueError(f"openvla predicts a 7-D action, got output features {self.output_features}")

    def get_optimizer_preset(self) -> AdamWConfig:
        return AdamWConfig(lr=self.optimizer_lr, weight_decay=self.optimizer_weight_decay)

    def get_scheduler_preset(self) -> None:
        return None

    @property
    def observation_delta_indices(self) -> None:
        return None

    @property
    def action_delta_indices(self) -> None:
        return None

    @property
    def reward_delta_indices(self) -> None:
        return None
