"""A perceptual distance on the tokenizer encoder's features: LPIPS's recipe (Zhang et al. 2018) with the project's
own trained encoder as the trunk, so it needs no download.

For each encoder stage the channel vector at every position is unit-normalised, and the squared difference between
the two images is summed over channels and averaged over space; the stages are averaged with uniform weights (no
learned linear heads, LPIPS's "baseline" variant). As ||a - b||^2 = 2 - 2 cos(a, b) for unit vectors, the result
divided by 4 lies in [0, 1]: 0 for identical images, 0.5 for orthogonal features.
"""

import copy

import torch
from torch import nn

from lerobot_roboscape.tokenizer.modeling_tokenizer import VisualTokenizer


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
