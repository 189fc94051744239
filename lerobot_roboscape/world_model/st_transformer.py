"""The spatial-temporal transformer block (Genie, Bruce et al. 2024, Fig. 4; with cross-attention to control
tokens as in RoboScape-R, Fig. 1). Tensors are named by layout: x_BTSC = (batch, time, space, channels)."""

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from einops import rearrange
from torch import nn

from lerobot_roboscape.world_model.configuration_world_model import WorldModelConfig

KV = tuple[torch.Tensor, torch.Tensor]  # keys (rotary-rotated) and values: (N, n_head, T, head_dim)


def rotate(x: torch.Tensor, positions: torch.Tensor) -> torch.Tensor:
    """Rotary position embedding of x (..., T, hs) at integer `positions` (T,). Angles are computed in float64 so
    that absolute frame positions of long rollouts stay exact; attention only sees their differences."""
    half = x.shape[-1] // 2
    freqs = 10000 ** (-torch.arange(half, device=x.device, dtype=torch.float64) / half)
    angles = positions.double()[:, None] * freqs[None]  # (T, hs/2)
    cos, sin = angles.cos().to(x.dtype), angles.sin().to(x.dtype)
    x1, x2 = x[..., :half], x[..., half:]
    return torch.cat([x1 * cos - x2 * sin, x1 * sin + x2 * cos], dim=-1)


@dataclass
class KVCache:
    """Keys and values of the last `window` frames of every layer, in a ring buffer: frame t lives in slot
    t % window. A new frame is written into its slot (overwriting the frame that leaves the window) and attends to
    the whole buffer, so generating a frame costs the same at step 10 and step 10000, and nothing is copied."""

    k: list[torch.Tensor]  # per layer (N, n_head, window, head_dim)
    v: list[torch.Tensor]
    frames: int  # frames committed so far; the frame being generated is number `frames`

    @classmethod
    def from_frames(cls, kvs: list[KV], window: int) -> "KVCache":
        """A cache holding the last window - 1 of the frames whose keys/values are `kvs` (T frames, from 0)."""
        T = kvs[0][0].shape[2]
        keep = range(max(0, T - (window - 1)), T)
        ks, vs = [], []
        for k, v in kvs:
            buffer_k = k.new_zeros(*k.shape[:2], window, k.shape[3])
            buffer_v = torch.zeros_like(buffer_k)
            for t in keep:
                buffer_k[:, :, t % window], buffer_v[:, :, t % window] = k[:, :, t], v[:, :, t]
            ks.append(buffer_k)
            vs.append(buffer_v)
        return cls(ks, vs, T)

    @property
    def window(self) -> int:
        return self.k[0].shape[2]

    @property
    def slot(self) -> int:
        return self.frames % self.window

    def mask(self, device) -> torch.Tensor | None:
        """Slots holding a frame (all of them once the window has filled)."""
        if self.frames >= self.window - 1:
            return None
        return (torch.arange(self.window, device=device) <= self.frames)[None, None, None]


class Attention(nn.Module):
    """Multi-head attention; self-attention when `context` is None."""

    def __init__(self, config: WorldModelConfig):
        super().__init__()
        self.n_head = config.n_head
        self.q = nn.Linear(config.d_model, config.d_model)
        self.kv = nn.Linear(config.d_model, 2 * config.d_model)
        self.proj = nn.Linear(config.d_model, config.d_model)
        self.dropout = config.dropout

    def heads(self, x):
        return rearrange(x, "n t (h d) -> n h t d", h=self.n_head)

    def forward(self, x_NTC, context_NLC=None, mask=None):
        context = x_NTC if context_NLC is None else context_NLC
        q = self.heads(self.q(x_NTC))
        k, v = map(self.heads, self.kv(context).chunk(2, dim=-1))
        y = F.scaled_dot_product_attention(q, k, v, attn_mask=mask, dropout_p=self.dropout if self.training else 0.0)
        return self.proj(rearrange(y, "n h t d -> n t (h d)"))


class TemporalAttention(Attention):
    """Causal self-attention over time with rotary positions (the frame's index in its rollout).

    Without a cache, frames 0..T-1 attend causally to each other (training, reading a prompt, recomputing a
    window) and their keys/values are returned. With a cache, one new frame attends to the cached frames.
    """

    def forward(self, x_NTC, cache: KVCache | None = None, layer: int = 0):
        q = self.heads(self.q(x_NTC))
        k, v = map(self.heads, self.kv(x_NTC).chunk(2, dim=-1))
        dropout = self.dropout if self.training else 0.0
        if cache is None:
            positions = torch.arange(q.shape[2], device=q.device)
            q, k = rotate(q, positions), rotate(k, positions)
            y = F.scaled_dot_product_attention(q, k, v, is_causal=True, dropout_p=dropout)
            return self.proj(rearrange(y, "n h t d -> n t (h d)")), (k, v)
        assert q.shape[2] == 1, "a cached step reads one new frame"
        position = torch.tensor([cache.frames], device=q.device)
        q, k = rotate(q, position), rotate(k, position)
        cache.k[layer][:, :, cache.slot] = k[:, :, 0]
        cache.v[layer][:, :, cache.slot] = v[:, :, 0]
        y = F.scaled_dot_product_attention(q, cache.k[layer], cache.v[layer], attn_mask=cache.mask(q.device))
        return self.proj(rearrange(y, "n h t d -> n t (h d)")), None


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
    frame's control tokens, MLP; each a pre-norm residual."""

    def __init__(self, config: WorldModelConfig):
        super().__init__()
        self.ln_spatial, self.spatial = nn.LayerNorm(config.d_model), Attention(config)
        self.ln_temporal, self.temporal = nn.LayerNorm(config.d_model), TemporalAttention(config)
        self.ln_cross, self.cross = nn.LayerNorm(config.d_model), Attention(config)
        self.ln_mlp, self.mlp = nn.LayerNorm(config.d_model), Mlp(config)

    def forward(self, x_BTSC, control_BTLC, control_mask_BTL=None, cache: KVCache | None = None, layer: int = 0):
        B, T, S, _ = x_BTSC.shape
        x_NSC = rearrange(x_BTSC, "b t s c -> (b t) s c")
        x_NSC = x_NSC + self.spatial(self.ln_spatial(x_NSC))

        x_NTC = rearrange(x_NSC, "(b t) s c -> (b s) t c", b=B)
        h, kv = self.temporal(self.ln_temporal(x_NTC), cache, layer)
        x_NSC = rearrange(x_NTC + h, "(b s) t c -> (b t) s c", b=B)

        control = rearrange(control_BTLC.expand(B, T, -1, -1), "b t l c -> (b t) l c")
        mask = None
        if control_mask_BTL is not None:
            mask = rearrange(control_mask_BTL.expand(B, T, -1), "b t l -> (b t) 1 1 l")
        x_NSC = x_NSC + self.cross(self.ln_cross(x_NSC), control, mask)
        x_NSC = x_NSC + self.mlp(self.ln_mlp(x_NSC))
        return rearrange(x_NSC, "(b t) s c -> b t s c", b=B), kv
