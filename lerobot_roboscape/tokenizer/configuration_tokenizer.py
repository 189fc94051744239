from dataclasses import dataclass

import draccus

from roboscape_core.errors import InvalidInputError


@dataclass
class TokenizerConfig(draccus.ChoiceRegistry):
    """A MAGVIT-2-style image tokenizer: convolutional encoder/decoder around lookup-free quantisation (LFQ).

    Each camera view is tokenized on its own into a `tokens_per_side` x `tokens_per_side` grid of codes; the world
    model lays the views' grids side by side (see `WorldModelConfig`). Choose a preset on the command line with
    `--tokenizer.type=tiny|paper`, then override any field.

    Args:
        image_size: side of the square camera images, in pixels.
        base_channels: channels of the first encoder level.
        channel_multipliers: channels of each level as multiples of `base_channels`; every level after the first
            halves the resolution, so the grid side is image_size / 2 ** (len - 1).
        num_res_blocks: residual blocks per level.
        codebook_bits: LFQ code width; the codebook holds 2 ** codebook_bits codes.
        object_weight: extra weight of the reconstruction error on the task object's pixels (dilated by a pixel),
            from the masks recorded with the dataset (`roboscape-collect --segmentation=true`); 0 trains without masks.
            A 7 px object is under 1% of a 64 px view: a pixel-averaged loss can drop it and lose almost nothing.
        perceptual_weight: weight of the LPIPS loss.
        entropy_weight: weight of LFQ's entropy loss (codebook usage and confident codes).
        commitment_weight: weight of LFQ's commitment loss.
        lpips_net: LPIPS trunk, "alex" or "vgg".
    """

    # Images.
    image_size: int = 64
    # Architecture.
    base_channels: int = 16
    channel_multipliers: tuple[int, ...] = (1, 2, 2, 4)
    num_res_blocks: int = 1
    codebook_bits: int = 8
    # Losses.
    object_weight: float = 0.0
    perceptual_weight: float = 0.1
    entropy_weight: float = 0.1
    commitment_weight: float = 0.25
    lpips_net: str = "alex"

    def __post_init__(self):
        self.channel_multipliers = tuple(self.channel_multipliers)
        if self.image_size % self.downsample:
            raise InvalidInputError(
                f"image_size={self.image_size} must be divisible by the downsampling factor {self.downsample} "
                f"(from channel_multipliers={self.channel_multipliers})"
            )
        if not 1 <= self.codebook_bits <= 16:
            raise InvalidInputError(
                f"codebook_bits must be in [1, 16] (tokens are stored as uint16), got {self.codebook_bits}"
            )

    @classmethod
    def default_choice_name(cls) -> str:
        return "tiny"  # `--tokenizer.base_channels=32` alone then edits the tiny preset

    @property
    def downsample(self) -> int:
        return 2 ** (len(self.channel_multipliers) - 1)

    @property
    def tokens_per_side(self) -> int:
        return self.image_size // self.downsample

    @property
    def codebook_size(self) -> int:
        return 2**self.codebook_bits


@TokenizerConfig.register_subclass("tiny")
@dataclass
class TinyTokenizerConfig(TokenizerConfig):
    """64 px views to 8x8 codes of 8 bits; trains on 2 CPU cores in minutes."""


@TokenizerConfig.register_subclass("bench")
@dataclass
class BenchTokenizerConfig(TokenizerConfig):
    """64 px views to 16x16 codes of 10 bits (4x4 px per code), so that a 4 cm object (about 7 px with the task
    suite's cameras) can survive reconstruction. Its losses were chosen by an ablation at equal steps on held-out
    OOD frames (docs/results/tokenizer/report.md): the object's pixels weigh 50x more (masks recorded with the
    dataset), and a lighter entropy loss (0.02) leaves the codes to the image instead of to uniform use. L1 without
    LPIPS: no pretrained trunk is available offline."""

    channel_multipliers: tuple[int, ...] = (1, 2, 4)
    codebook_bits: int = 10
    object_weight: float = 50.0
    entropy_weight: float = 0.02
    perceptual_weight: float = 0.0


@TokenizerConfig.register_subclass("paper")
@dataclass
class PaperTokenizerConfig(TokenizerConfig):
    """128 px views to 16x16 codes of 12 bits (the paper's 16x16 token grid)."""

    image_size: int = 128
    base_channels: int = 128
    num_res_blocks: int = 2
    codebook_bits: int = 12
