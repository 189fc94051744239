"""A perceptual distance on the tokenizer encoder's features: LPIPS's recipe (Zhang et al. 2018) with the project's
own trained encoder as the trunk, so it needs no download.

For each encoder stage the channel vector at every position is unit-normalised, and the squared difference between
the two images is summed over channels and averaged over space; the stages are averaged with uniform weights (no
learned linear heads, LPIPS's "baseline" variant). As ||a - b||^2 = 2 - 2 cos(a, b) for unit vectors, the result
divided by 4 lies in [0, 1]: 0 for identical images, 0.5 for orthogonal features.
"""

import copy
import logging
from pathlib import Path

import torch
from torch import nn

from lerobot_roboscape.metrics.perceptual import default_trunk_path, load_lpips
from lerobot_roboscape.tokenizer.modeling_tokenizer import VisualTokenizer
from roboscape_core.errors import InvalidInputError

logger = logging.getLogger(__name__)
SIMILARITIES = ("auto", "lpips", "tokenizer", "pixel")  # of the env's reward (`load_similarity`)


def _unit_channels(x: torch.Tensor, eps: float = 1e-10) -> torch.Tensor:
    return x / (x.pow(2).sum(1, keepdim=True).sqrt() + eps)


class TokenizerPerceptualDistance(nn.Module):
    """Frozen distance with the call convention of `lpips.LPIPS`: (B, 3, H, W) images in [-1, 1] (the range the
    tokenizer encoder is fed) -> (B, 1, 1, 1) distances in [0, 1].

    The stages are each resolution level's output (before it is downsampled) and the latent the quantiser reads.
    The encoder is copied, so freezing it and moving it across devices leaves the tokenizer untouched.
    """

    name = "tokenizer"  # which similarity a report used; `load_lpips` names its metrics the same way

    def __init__(self, tokenizer: VisualTokenizer):
        super().__init__()
        self.layers = copy.deepcopy(tokenizer.encoder.layers)
        downsamples = [i for i, m in enumerate(self.layers) if isinstance(m, nn.Conv2d) and m.stride == (2, 2)]
        self.stage_ends = {i - 1 for i in downsamples} | {len(self.layers) - 1}
        self.eval().requires_grad_(False)

    def stages(self, images: torch.Tensor) -> list[torch.Tensor]:
        """(B, 3, H, W) in [-1, 1] -> the activations of every stage, each (B, C_stage, H_stage, W_stage)."""
        features, x = [], images
        for i, layer in enumerate(self.layers):
            x = layer(x)
            if i in self.stage_ends:
                features.append(x)
        return features

    @torch.no_grad()
    def forward(self, images0: torch.Tensor, images1: torch.Tensor) -> torch.Tensor:
        per_stage = [
            (_unit_channels(f0) - _unit_channels(f1)).pow(2).sum(1).mean((1, 2)) / 4  # (B,)
            for f0, f1 in zip(self.stages(images0), self.stages(images1), strict=True)
        ]
        return torch.stack(per_stage).mean(0).view(-1, 1, 1, 1)


def frame_distance(distance: nn.Module, frames: torch.Tensor, others: torch.Tensor) -> torch.Tensor:
    """A distance of `load_similarity` between frames of several camera views, (B, n_cameras, 3, H, W) in [0, 1]
    each: the views' distances averaged, (B,)."""
    B, n = frames.shape[:2]
    return distance(frames.flatten(0, 1) * 2 - 1, others.flatten(0, 1) * 2 - 1).float().reshape(B, n).mean(1)


class PixelDistance(nn.Module):
    """The plainest offline distance, a baseline for the perceptual ones: the mean squared difference of the two
    images' pixels, (B, 3, H, W) in [-1, 1] -> (B, 1, 1, 1) in [0, 1]."""

    name = "pixel"

    @torch.no_grad()
    def forward(self, images0: torch.Tensor, images1: torch.Tensor) -> torch.Tensor:
        return ((images0 - images1).pow(2).mean((1, 2, 3)) / 4).view(-1, 1, 1, 1)


def load_similarity(
    kind: str,
    tokenizer: VisualTokenizer | None,
    lpips_net: str = "alex",
    lpips_weights: str | Path | None = None,
    allow_random_lpips: bool = False,
) -> nn.Module:
    """The perceptual distance a reward or report should use, frozen and in eval mode.

    Every metric returned takes two (B, 3, H, W) image batches in [-1, 1] and returns (B, 1, 1, 1) distances, 0 for
    identical images, and has a `name` saying which similarity it is ("lpips (alex)", "tokenizer", ...).

    Args:
        kind: one of `SIMILARITIES`. "lpips": LPIPS (see `load_lpips`), refused without trunk weights unless
            `allow_random_lpips`. "tokenizer": `TokenizerPerceptualDistance` on `tokenizer`'s encoder. "auto": LPIPS
            when its trunk weights are found (`lpips_weights`, else the torch hub cache), else the tokenizer
            distance; it never picks a random trunk, and a named `lpips_weights` that is missing is an error.
            "pixel": `PixelDistance`, the mean squared pixel difference (a baseline; no trunk at all).
        tokenizer: the trained tokenizer; needed by "tokenizer", and by "auto" when no LPIPS weights are found.
        lpips_net: LPIPS trunk, "alex" or "vgg".
        lpips_weights: torchvision's trunk weights (.pth or .safetensors); default: the torch hub cache.
        allow_random_lpips: with kind="lpips", use a random trunk when no weights are found (not perceptual).
    """
    if kind not in SIMILARITIES:
        raise InvalidInputError(f"similarity must be one of {SIMILARITIES}, got {kind!r}")
    if kind == "auto":
        cached = default_trunk_path(lpips_net)
        if lpips_weights is not None or cached.is_file():
            kind = "lpips"
            logger.info("Perceptual similarity (auto): LPIPS (%s) from %s", lpips_net, lpips_weights or cached)
        else:
            kind = "tokenizer"
            logger.info("Perceptual similarity (auto): tokenizer features (no LPIPS weights at %s)", cached)
    if kind == "lpips":
        return load_lpips(lpips_net, lpips_weights, allow_random_lpips)
    if kind == "pixel":
        return PixelDistance()
    if tokenizer is None:
        raise InvalidInputError("the tokenizer similarity needs a trained tokenizer, got None")
    return TokenizerPerceptualDistance(tokenizer)
