"""The spatial-temporal transformer block (Genie, Bruce et al. 2024, Fig. 4; with cross-attention to control
tokens as in RoboScape-R, Fig. 1).

Tensors are named by layout: B batch, T time (frames), S space (a frame's tokens), C channels, L control tokens,
H heads, D head width, W the cache's window. Attention runs over rows of two kinds: F = B*T rows, one per frame, for
spatial and cross-attention; P = B*S rows, one per token position, for temporal attention.
"""

import math
from dataclasses import dataclass, field

import torch
import torch.nn.functional as F
from einops import rearrange
from torch import nn

from lerobot_roboscape.world_model.configuration_world_model import WorldModelConfig
from lerobot_roboscape.world_model.control_encoders import Control


def rotary(positions: torch.Tensor, width: int, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """cos and sin (T, width / 2) of the rotary embedding at integer frame `positions` (T,). Angles are computed in
    float64 so that absolute positions of long rollouts stay exact; attention only sees their differences."""
    half = width // 2
    freqs = 10000 ** (-torch.arange(half, device=positions.device, dtype=torch.float64) / half)
    angles = positions.double()[:, None] * freqs[None]
    return angles.cos().to(dtype), angles.sin().to(dtype)


def rotate(x: torch.Tensor, cos: torch.Tensor, sin: torch.Tensor) -> torch.Tensor:
    """Rotate the last dimension of x (..., T, D) by the angles of `rotary` (T, D / 2)."""
    x1, x2 = x.chunk(2, dim=-1)
    return torch.cat([x1 * cos - x2 * sin, x1 * sin + x2 * cos], dim=-1)


@dataclass
class LayerCache:
    """One block's keys and values of the last `window` frames: frame t lives in slot t % window."""

    k: torch.Tensor  # (P, H, W, D)
    v: torch.Tensor
    ring: "KVCache" = field(repr=False)


class KVCache:
    """Every block's keys and values of the last `window` frames, in ring buffers. A new frame is written into its
    slot (overwriting the frame that leaves the window) and attends to the whole buffer, so generating a frame
    costs the same at step 10 and step 10000, and nothing is copied. `layers[i]` is block i's view.

    A cache starts empty. The prompt's pass writes each block's keys and values into its ring as the block computes
    them (`fill`), in the dtype they were computed in, so no block's prompt keys outlive it: the cache's memory is
    its rings (`nbytes`), allocated whole when the first block fills. Filling again with the same shapes (a new
    episode) reuses them.

    Where the frame being computed sits (its slot, which slots hold no frame yet, its rotary angles) lives in tensors on
    the rings' device, updated in place by `advance`: a frame's work reads no Python state that changes from frame
    to frame, so it can be captured once as a CUDA graph and replayed (world_model/rollout.py)."""

    def __init__(self, n_layer: int, window: int):
        self.n_layer, self.window = n_layer, window
        self.frames = 0  # frames committed so far; the frame being computed is number `frames`
        self.layers: list[LayerCache] = []
        self.graphs: dict = {}  # CUDA graphs recorded against these rings (world_model/rollout.py), dropped with them

    @staticmethod
    def nbytes(n_layer: int, rows: int, d_model: int, window: int, itemsize: int) -> int:
        """Bytes of the rings: keys and values of `window` frames, for every layer and row (token position)."""
        return n_layer * 2 * rows * window * d_model * itemsize

    def fill(self, layer: int, k: torch.Tensor, v: torch.Tensor) -> None:
        """Block `layer`'s keys and values (P, H, T, D) of the T prompt frames: the last window - 1 go to their
        slots. After the last block, the cache holds T frames."""
        P, H, T, D = k.shape
        if layer == 0 and not self._fits(k):
            self.layers = [
                LayerCache(k.new_zeros(P, H, self.window, D), k.new_zeros(P, H, self.window, D), self)
                for _ in range(self.n_layer)
            ]
            self.position = torch.zeros(1, dtype=torch.long, device=k.device)  # the frame being computed
            self.slot = torch.zeros_like(self.position)
            self.empty = torch.zeros(self.window, dtype=torch.bool, device=k.device)  # slots holding no frame yet
            self.cos, self.sin = rotary(self.position, D, k.dtype)
            self.graphs = {}
        keep = torch.arange(max(0, T - (self.window - 1)), T, device=k.device)
        ring = self.layers[layer]
        ring.k[:, :, keep % self.window], ring.v[:, :, keep % self.window] = k[:, :, keep], v[:, :, keep]
        if layer == self.n_layer - 1:
            self.frames = T
            self.position.fill_(T - 1)
            self.advance()

    def _fits(self, k: torch.Tensor) -> bool:
        """The rings already hold frames of this shape, dtype and device (a new episode of the same rollout)."""
        if not self.layers:
            return False
        ring = self.layers[0].k
        P, H, _, D = k.shape
        return ring.shape == (P, H, self.window, D) and ring.dtype == k.dtype and ring.device == k.device

    @property
    def allocated_bytes(self) -> int:
        return sum(t.numel() * t.element_size() for ring in self.layers for t in (ring.k, ring.v))

    def advance(self) -> None:
        """Move the device-side state to the next frame, in place (no host sync, no new tensors kept)."""
        self.position += 1
        torch.remainder(self.position, self.window, out=self.slot)
        slots = torch.arange(self.window, device=self.position.device)
        # Until the window has filled, the slots after the new frame's hold nothing yet.
        self.empty.copy_((slots > self.position) & (self.position < self.window - 1))
        cos, sin = rotary(self.position, self.cos.shape[-1] * 2, self.cos.dtype)
        self.cos.copy_(cos)
        self.sin.copy_(sin)

    def commit(self) -> None:
        """The frame just computed stays: its keys and values are already in its slot."""
        self.frames += 1
        self.advance()


class Attention(nn.Module):
    """Multi-head attention; self-attention when `context` is None."""

    def __init__(self, config: WorldModelConfig):
        super().__init__()
        self.n_head = config.n_head
        self.q = nn.Linear(config.d_model, config.d_model)
        self.kv = nn.Linear(config.d_model, 2 * config.d_model)
        self.proj = nn.Linear(config.d_model, config.d_model)
        self.dropout = config.dropout

    def heads(self, x_NTC):
        return rearrange(x_NTC, "n t (h d) -> n h t d", h=self.n_head)

    def merge(self, y_NHTD):
        return self.proj(rearrange(y_NHTD, "n h t d -> n t (h d)"))

    def forward(self, x_NTC, context_NLC=None, mask=None):
        context = x_NTC if context_NLC is None else context_NLC
        q = self.heads(self.q(x_NTC))
        k, v = map(self.heads, self.kv(context).chunk(2, dim=-1))
        dropout = self.dropout if self.training else 0.0
        return self.merge(F.scaled_dot_product_attention(q, k, v, attn_mask=mask, dropout_p=dropout))


class TemporalAttention(Attention):
    """Causal self-attention over time with rotary positions (the frame's index in its rollout).

    Without a cache, frames 0..T-1 attend causally to each other (training, reading a prompt, recomputing a
    window) and their keys/values are returned. With a cache, one new frame attends to the cached frames.
    """

    def forward(self, x_PTC, cache: LayerCache | None = None):
        q = self.heads(self.q(x_PTC))
        k, v = map(self.heads, self.kv(x_PTC).chunk(2, dim=-1))
        if cache is None:
            T = q.shape[2]
            cos, sin = rotary(torch.arange(T, device=q.device), q.shape[-1], q.dtype)
            q, k = rotate(q, cos, sin), rotate(k, cos, sin)
            # Two matmuls, not the fused kernel: there is a row per token position (B * S, 131,072 at batch 256),
            # beyond the 65,535 batch rows CUDA's fused attention kernels launch, and T is a handful of frames.
            scores = (q @ k.transpose(-1, -2)) * q.shape[-1] ** -0.5  # (P, H, T, T)
            future = torch.ones(T, T, dtype=torch.bool, device=q.device).triu(1)
            weights = F.dropout(scores.masked_fill(future, -math.inf).softmax(-1), self.dropout, self.training)
            return self.merge(weights @ v), (k, v)
        if q.shape[2] != 1:
            raise ValueError(f"a cached step reads one new frame, got {q.shape[2]}")
        ring = cache.ring
        q = rotate(q, ring.cos, ring.sin)
        cache.k.index_copy_(2, ring.slot, rotate(k, ring.cos, ring.sin).to(cache.k.dtype))
        cache.v.index_copy_(2, ring.slot, v.to(cache.v.dtype))
        # One query against `window` keys per row: two small matmuls beat the fused kernel here (a frame at batch 16
        # on 2 CPU cores: 1.5 s against 1.75 s, measured).
        scores = (q @ cache.k.transpose(-1, -2)) * q.shape[-1] ** -0.5
        scores = scores.masked_fill(ring.empty, -math.inf)
        return self.merge(scores.softmax(-1) @ cache.v), None


class Mlp(nn.Module):
    def __init__(self, config: WorldModelConfig):
        super().__init__()
        hidden = config.mlp_ratio * config.d_model
        self.net = nn.Sequential(
            nn.Linear(config.d_model, hidden), nn.GELU(), nn.Linear(hidden, config.d_model), nn.Dropout(config.dropout)
        )

    def forward(self, x):
        return self.net(x)


class STBlock(nn.Module):
    """Spatial attention within each frame, causal temporal attention per token position, cross-attention to the
    frame's control tokens, MLP; each a pre-norm residual.

    With `adaln`, every one of the four LayerNorms is modulated by the frame's pooled control (DiT's adaptive
    LayerNorm, per frame as in IRASim): x + gate * sublayer(LN(x) * (1 + scale) + shift), so the control reaches
    every token of its frame in every block, not only through the cross-attention's softmax.
    """

    N_SUBLAYERS = 4  # spatial, temporal, cross, mlp

    def __init__(self, config: WorldModelConfig):
        super().__init__()
        C = config.d_model
        self.ln_spatial, self.spatial = nn.LayerNorm(C), Attention(config)
        self.ln_temporal, self.temporal = nn.LayerNorm(C), TemporalAttention(config)
        self.ln_cross, self.cross = nn.LayerNorm(C), Attention(config)
        self.ln_mlp, self.mlp = nn.LayerNorm(C), Mlp(config)
        self.ln_context = nn.LayerNorm(C) if config.normalize_control else nn.Identity()
        self.modulation = None
        if config.adaln != "none":
            self.modulation = nn.Sequential(nn.SiLU(), nn.Linear(C, 3 * self.N_SUBLAYERS * C))

    def zero_init_modulation(self):
        """The control starts with no effect (DiT): called after the model's normal initialisation."""
        if self.modulation is not None:
            nn.init.zeros_(self.modulation[1].weight)
            nn.init.zeros_(self.modulation[1].bias)

    def forward(self, x_BTSC, control: Control, cache: LayerCache | None = None):
        B, T, S, _ = x_BTSC.shape
        if self.modulation is None:
            mods = [(None, None, None)] * self.N_SUBLAYERS
        else:  # (B, T or 1, 12C) -> 4 x (shift, scale, gate), each (B, T or 1, 1, C)
            chunks = self.modulation(control.pooled)[:, :, None].chunk(3 * self.N_SUBLAYERS, dim=-1)
            mods = [chunks[3 * i : 3 * i + 3] for i in range(self.N_SUBLAYERS)]

        def norm(ln, x, mod):
            shift, scale, _ = mod
            return ln(x) if shift is None else ln(x) * (1 + scale) + shift

        def gated(h, mod):
            return h if mod[2] is None else (1 + mod[2]) * h

        h_BTSC = rearrange(norm(self.ln_spatial, x_BTSC, mods[0]), "b t s c -> (b t) s c")
        x_BTSC = x_BTSC + gated(rearrange(self.spatial(h_BTSC), "(b t) s c -> b t s c", b=B), mods[0])

        h_PTC = rearrange(norm(self.ln_temporal, x_BTSC, mods[1]), "b t s c -> (b s) t c")
        h_PTC, kv = self.temporal(h_PTC, cache)
        x_BTSC = x_BTSC + gated(rearrange(h_PTC, "(b s) t c -> b t s c", b=B), mods[1])

        context_FLC = rearrange(self.ln_context(control.tokens).expand(B, T, -1, -1), "b t l c -> (b t) l c")
        mask = None
        if control.mask is not None:
            mask = rearrange(control.mask.expand(B, T, -1), "b t l -> (b t) 1 1 l")
        h_FSC = self.cross(rearrange(norm(self.ln_cross, x_BTSC, mods[2]), "b t s c -> (b t) s c"), context_FLC, mask)
        x_BTSC = x_BTSC + gated(rearrange(h_FSC, "(b t) s c -> b t s c", b=B), mods[2])
        x_BTSC = x_BTSC + gated(self.mlp(norm(self.ln_mlp, x_BTSC, mods[3])), mods[3])
        return x_BTSC, kv
