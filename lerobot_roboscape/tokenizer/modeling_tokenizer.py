"""MAGVIT-2-style image tokenizer (Yu et al. 2023): residual conv encoder, lookup-free quantisation, conv decoder.

Images enter as float (B, 3, H, W) in [0, 1]; codes leave as integer grids (B, h, w) with h = H / downsample.
"""

import math
from typing import NamedTuple

import numpy as np
import torch
from einops import rearrange
from torch import nn
from vector_quantize_pytorch import LFQ

from lerobot_roboscape.dataset.segmentation import OBJECT
from lerobot_roboscape.io.weights import CheckedHubMixin
from lerobot_roboscape.metrics.image_fidelity import OBJECT_DILATION, dilate
from lerobot_roboscape.tokenizer.configuration_tokenizer import TokenizerConfig


def _norm(channels: int) -> nn.GroupNorm:
    return nn.GroupNorm(math.gcd(32, channels), channels)


def encoder_input(images: torch.Tensor) -> torch.Tensor:
    """Images in [0, 1] -> the encoder's input range, [-1, 1]."""
    return images * 2 - 1


class ResBlock(nn.Module):
    def __init__(self, c_in: int, c_out: int):
        super().__init__()
        self.block = nn.Sequential(
            _norm(c_in),
            nn.SiLU(),
            nn.Conv2d(c_in, c_out, 3, padding=1),
            _norm(c_out),
            nn.SiLU(),
            nn.Conv2d(c_out, c_out, 3, padding=1),
        )
        self.skip = nn.Conv2d(c_in, c_out, 1) if c_in != c_out else nn.Identity()

    def forward(self, x):
        return self.skip(x) + self.block(x)


class Encoder(nn.Module):
    def __init__(self, config: TokenizerConfig):
        super().__init__()
        widths = [config.base_channels * m for m in config.channel_multipliers]
        layers: list[nn.Module] = [nn.Conv2d(3, widths[0], 3, padding=1)]
        c = widths[0]
        for level, width in enumerate(widths):
            for _ in range(config.num_res_blocks):
                layers.append(ResBlock(c, width))
                c = width
            if level < len(widths) - 1:
                layers.append(nn.Conv2d(c, c, 4, stride=2, padding=1))
        layers += [ResBlock(c, c), _norm(c), nn.SiLU(), nn.Conv2d(c, config.codebook_bits, 1)]
        self.layers = nn.Sequential(*layers)

    def forward(self, x):
        return self.layers(x)


class Decoder(nn.Module):
    def __init__(self, config: TokenizerConfig):
        super().__init__()
        widths = [config.base_channels * m for m in config.channel_multipliers][::-1]
        c = widths[0]
        layers: list[nn.Module] = [nn.Conv2d(config.codebook_bits, c, 3, padding=1), ResBlock(c, c)]
        for level, width in enumerate(widths):
            for _ in range(config.num_res_blocks):
                layers.append(ResBlock(c, width))
                c = width
            if level < len(widths) - 1:
                # Depth-to-space upsampling, as MAGVIT-2 does (no checkerboard from transposed convolutions).
                layers += [nn.Conv2d(c, 4 * c, 3, padding=1), nn.PixelShuffle(2)]
        layers += [_norm(c), nn.SiLU(), nn.Conv2d(c, 3, 3, padding=1)]
        self.layers = nn.Sequential(*layers)

    def forward(self, x):
        return self.layers(x)


class TokenizerOutput(NamedTuple):
    reconstruction: torch.Tensor  # (B, 3, H, W) in [0, 1]
    indices: torch.Tensor  # (B, h, w) long
    quantizer_loss: torch.Tensor  # LFQ entropy + commitment loss, weighted


class VisualTokenizer(nn.Module, CheckedHubMixin, library_name="lerobot-roboscape", tags=["lerobot", "tokenizer"]):
    def __init__(self, config: TokenizerConfig):
        super().__init__()
        self.config = config
        self.encoder = Encoder(config)
        self.decoder = Decoder(config)
        self.quantizer = LFQ(
            dim=config.codebook_bits,
            codebook_size=config.codebook_size,
            entropy_loss_weight=config.entropy_weight,
            commitment_loss_weight=config.commitment_weight,
        )

    def _check_images(self, images: torch.Tensor):
        size = self.config.image_size
        if images.ndim != 4 or images.shape[1] != 3 or images.shape[-2:] != (size, size):
            raise ValueError(f"tokenizer expects images of shape (B, 3, {size}, {size}), got {tuple(images.shape)}")

    def _quantize(self, images: torch.Tensor):
        self._check_images(images)
        latents = self.encoder(encoder_input(images))
        h = latents.shape[-1]
        codes, indices, aux_loss = self.quantizer(rearrange(latents, "b d h w -> b (h w) d"))
        return rearrange(codes, "b (h w) d -> b d h w", h=h), rearrange(indices, "b (h w) -> b h w", h=h), aux_loss

    def forward(self, images: torch.Tensor) -> TokenizerOutput:
        codes, indices, aux_loss = self._quantize(images)
        reconstruction = (self.decoder(codes) + 1) / 2
        return TokenizerOutput(reconstruction, indices, aux_loss)

    def compute_loss(
        self, images: torch.Tensor, lpips_metric: nn.Module | None = None, masks: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, dict]:
        """Reconstruction (L1, the object's pixels weighted up when `masks` (B, H, W) labels are given) + perceptual
        (LPIPS, when a metric is given) + quantiser losses."""
        out = self(images)
        error = (out.reconstruction - images).abs().mean(1)  # (B, H, W)
        l1 = error.mean()
        loss = l1 + out.quantizer_loss
        logs = {"l1": l1.item(), "quantizer": out.quantizer_loss.item()}
        if self.config.object_weight > 0:
            if masks is None:
                raise ValueError("object_weight > 0 needs the frames' segmentation masks")
            region = dilate(masks == OBJECT, OBJECT_DILATION).float()
            object_l1 = (error * region).sum() / region.sum().clamp_min(1)
            loss = loss + self.config.object_weight * (error * region).mean()
            logs["object_l1"] = object_l1.item()
        if lpips_metric is not None and self.config.perceptual_weight > 0:
            perceptual = lpips_metric(out.reconstruction * 2 - 1, images * 2 - 1).mean()
            loss = loss + self.config.perceptual_weight * perceptual
            logs["lpips"] = perceptual.item()
        logs["loss"] = loss.item()
        return loss, logs

    @torch.no_grad()
    def encode(self, images: torch.Tensor) -> torch.Tensor:
        """(B, 3, H, W) float in [0, 1] or uint8 -> (B, h, w) long codes."""
        if images.dtype == torch.uint8:
            images = images.float() / 255
        return self._quantize(images)[1]

    def indices_to_codes(self, indices: torch.Tensor) -> torch.Tensor:
        """(B, h, w) codes -> (B, codebook_bits, h, w) quantised latents."""
        if indices.min() < 0 or indices.max() >= self.config.codebook_size:
            raise ValueError(
                f"token ids must be in [0, {self.config.codebook_size}), got [{indices.min()}, {indices.max()}]"
            )
        codes = self.quantizer.indices_to_codes(indices.flatten(1).long())  # (B, h * w, bits)
        return rearrange(codes, "b (h w) d -> b d h w", h=indices.shape[1])

    @torch.no_grad()
    def decode(self, indices: torch.Tensor) -> torch.Tensor:
        """(B, h, w) codes -> (B, 3, H, W) float images in [0, 1]."""
        return ((self.decoder(self.indices_to_codes(indices)) + 1) / 2).clamp(0, 1)

    @torch.no_grad()
    def encode_views(self, views: list[torch.Tensor]) -> torch.Tensor:
        """The camera views of the same T frames, each (T, 3, H, W), -> (T, S) tokens with the views' grids side
        by side (the world model's frame layout)."""
        return torch.stack([self.encode(v) for v in views], 1).flatten(1)

    @torch.no_grad()
    def encode_frames(self, views: list[np.ndarray]) -> torch.Tensor:
        """The camera views of the same T frames as recorded, each (T, H, W, 3) uint8, -> (T, S) tokens on the
        tokenizer's device (`encode_views`)."""
        device = next(self.parameters()).device
        return self.encode_views([torch.from_numpy(v).permute(0, 3, 1, 2).to(device) for v in views])

    @torch.no_grad()
    def decode_views(self, tokens_TS: torch.Tensor, n_cameras: int) -> torch.Tensor:
        """(T, S) frame tokens -> (T, n_cameras, 3, H, W) images in [0, 1]; the inverse of `encode_views`."""
        side = self.config.tokens_per_side
        return self.decode(tokens_TS.reshape(-1, side, side)).unflatten(0, (-1, n_cameras))
