"""The world model's training objective on its codes: which positions a clip masks (MaskGIT's cosine schedule per
frame, some frames left clean, the first always the prompt), which unmasked codes it corrupts, and the loss on the
masked codes, weighted up where they changed since the previous frame."""

import math
from collections.abc import Callable

import torch
import torch.nn.functional as F

from lerobot_roboscape.world_model.configuration_world_model import WorldModelConfig


def masked_inputs(
    tokens_BTS: torch.Tensor, c: WorldModelConfig, ungroup: Callable[[torch.Tensor], torch.Tensor]
) -> tuple[torch.Tensor, torch.Tensor]:
    """(the clip's inputs, its mask (B, T, S) bool): positions of frames after the first masked at a MaskGIT ratio
    each, or left clean with clean_frame_prob (a position's codes masked together, `ungroup` spreading a position's
    flag over them); a share of the codes left unmasked, drawn per clip up to corrupt_max, replaced by random
    codes (with corrupt_held the same codes by the same random ones in every frame of the clip)."""
    B, T, S = tokens_BTS.shape
    device = tokens_BTS.device
    ratio = torch.cos(math.pi / 2 * torch.rand(B, T, 1, device=device))  # MaskGIT cosine schedule
    ratio = ratio * (torch.rand(B, T, 1, device=device) >= c.clean_frame_prob)
    ratio[:, 0] = 0.0  # the first frame is the prompt
    masked_BTN = torch.rand(B, T, c.positions_per_frame, device=device) < ratio
    mask = ungroup(masked_BTN[..., None].expand(-1, -1, -1, c.codes_per_position))
    inputs = tokens_BTS
    if c.corrupt_max > 0:
        rate = c.corrupt_max * torch.rand(B, 1, 1, device=device)
        if c.corrupt_held:
            corrupt = torch.rand(B, 1, S, device=device) < rate
            noise = torch.randint(c.vocab_size, (B, 1, S), device=device).expand(B, T, S)
        else:
            corrupt, noise = torch.rand(B, T, S, device=device) < rate, torch.randint_like(tokens_BTS, c.vocab_size)
        inputs = torch.where(corrupt & ~mask, noise, tokens_BTS)
    return inputs.masked_fill(mask, c.mask_token_id), mask


def changed_codes(tokens_BTS: torch.Tensor) -> torch.Tensor:
    """(B, T, S) bool: the codes that differ from the previous frame's at the same place (none in the first)."""
    changed = torch.zeros_like(tokens_BTS, dtype=torch.bool)
    changed[:, 1:] = tokens_BTS[:, 1:] != tokens_BTS[:, :-1]
    return changed


def masked_token_loss(
    logits_RGV: torch.Tensor,
    tokens_RG: torch.Tensor,
    masked_RG: torch.Tensor,
    changed_RG: torch.Tensor,
    changed_weight: float,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """The cross-entropy of the masked codes of R positions (G codes each), those that changed since the previous
    frame weighing changed_weight, and its logs (the loss, the accuracy on masked codes and on changed ones:
    copying the previous frame scores 0 there). Weights, not boolean indexing, so that it never waits on the
    device; the caller may pass the masked positions only (masked_RG then all true)."""
    masked, masked_changed = masked_RG.float(), (masked_RG & changed_RG).float()
    weight = masked + (changed_weight - 1) * masked_changed
    token_ce = F.cross_entropy(logits_RGV.flatten(0, 1).float(), tokens_RG.flatten(), reduction="none")
    token_ce = token_ce.view_as(weight)
    loss = (weight * token_ce).sum() / weight.sum().clamp(min=1e-6)
    hits = (logits_RGV.argmax(-1) == tokens_RG).float()
    n_masked, n_changed = masked.sum(), masked_changed.sum()
    accuracy = (hits * masked).sum() / n_masked.clamp(min=1)
    changed_accuracy = torch.where(n_changed > 0, (hits * masked_changed).sum() / n_changed.clamp(min=1), accuracy)
    return loss, {"token_ce": loss, "token_acc": accuracy, "changed_acc": changed_accuracy}
