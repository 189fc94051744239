"""The spatial-temporal transformer block (Genie, Bruce et al. 2024, Fig. 4; with cross-attention to control
tokens as in RoboScape-R, Fig. 1). Tensors are named by layout: x_BTSC = (batch, time, space, channels)."""

import torch
import torch.nn.functional as F
from einops import rearrange
from torch import nn

from lerobot_roboscape.world_model.configuration_world_model import WorldModelConfig

KV = tuple[torch.Tensor, torch.Tensor]  # keys, values: (N, n_head, T, head_dim), before the rotary rotation


def rotate(x: torch.Tensor, positions: torch.Tensor) -> torch.Tensor:
    """Rotary position embedding of x (..., T, hs) at integer `positions` (T,)."""
    half = x.shape[-1] // 2
    freqs = 10000 ** (-torch.arange(half, device=x.device, dtype=torch.float32) / half)
    angles = positions.float()[:, None] * freqs[None]  # (T, hs/2)
    cos, sin = angles.cos().to(x.dtype), angles.sin().to(x.dtype)
    x1, x2 = x[..., :half], x[..., half:]
    return torch.cat([x1 * cos - x2 * sin, x1 * sin + x2 * cos], dim=-1)


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
    """Causal self-attention over time with rotary positions counted from the oldest frame in view.

    `past` holds earlier frames' keys and values, so only new frames are computed; positions restart at 0 at the
    window's oldest frame, so a sliding window sees the same relative positions as training clips.
    """

    def forward(self, x_NTC, past: KV | None = None):
        q = self.heads(self.q(x_NTC))
        k_new, v_new = map(self.heads, self.kv(x_NTC).chunk(2, dim=-1))
        k, v = (k_new, v_new) if past is None else (torch.cat([past[0], k_new], 2), torch.cat([past[1], v_new], 2))
        t_new, t_all = q.shape[2], k.shape[2]
        positions = torch.arange(t_all, device=x_NTC.device)
        q, k = rotate(q, positions[t_all - t_new :]), rotate(k, positions)
        if t_new == 1:
            mask, causal = None, False
        elif t_new == t_all:
            mask, causal = None, True
        else:  # several new frames after cached ones: frame i sees the past and new frames up to itself
            mask, causal = positions[None, :] <= positions[t_all - t_new :, None], False
        y = F.scaled_dot_product_attention(q, k, v, attn_mask=mask, is_causal=causal,
                                           dropout_p=self.dropout if self.training else 0.0)
        return self.proj(rearrange(y, "n h t d -> n t (h d)")), (k_new, v_new)


class Mlp(nn.Module):
    def __init__(self, config: WorldModelConfig):
        super().__init__()
        hidden = config.mlp_ratio * config.d_model
        self.net = nn.Sequential(nn.Linear(config.d_model, hidden), nn.GELU(), nn.Linear(hidden, config.d_model),
                                 nn.Dropout(config.dropout))

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

    def forward(self, x_BTSC, control_BTLC, control_mask_BTL=None, past: KV | None = None):
        B, T, S, _ = x_BTSC.shape
        x_NSC = rearrange(x_BTSC, "b t s c -> (b t) s c")
        x_NSC = x_NSC + self.spatial(self.ln_spatial(x_NSC))

        x_NTC = rearrange(x_NSC, "(b t) s c -> (b s) t c", b=B)
        h, kv = self.temporal(self.ln_temporal(x_NTC), past)
        x_NSC = rearrange(x_NTC + h, "(b s) t c -> (b t) s c", b=B)

        control = rearrange(control_BTLC.expand(B, T, -1, -1), "b t l c -> (b t) l c")
        mask = None
        if control_mask_BTL is not None:
            mask = rearrange(control_mask_BTL.expand(B, T, -1), "b t l -> (b t) 1 1 l")
        x_NSC = x_NSC + self.cross(self.ln_cross(x_NSC), control, mask)
        x_NSC = x_NSC + self.mlp(self.ln_mlp(x_NSC))
        return rearrange(x_NSC, "(b t) s c -> b t s c", b=B), kv
