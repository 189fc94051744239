"""A running generation of a world model: start from prompt frames, predict the next frame by MaskGIT decoding,
observe known frames, slide the window.

With the key/value cache (the default) a new frame is computed against the cached keys and values of the frames
before it. Without it, every step re-reads the whole window of past frames, as the paper's code (1xgpt's
`STMaskGIT.generate`) does. Both give the same tokens while the rollout fits in the window; past it, a cached frame
keeps the keys and values it was computed with (its own window of context), where recomputing re-reads the oldest
frames of the window without theirs.
"""

import math
from dataclasses import dataclass

import torch
from torch import nn

from lerobot_roboscape.world_model.control_encoders import Control
from lerobot_roboscape.world_model.st_transformer import KVCache


@dataclass
class Rollout:
    """What a running generation remembers: the last `window - 1` frames as tokens, their controls, and (with the
    cache) every layer's keys and values of those frames."""

    model: nn.Module  # an STWorldModel (not imported: it imports this module to generate)
    tokens: torch.Tensor  # (B, T, S) long
    control: Control  # (B, T, L, C) for the action model; (B, 1, L, C) shared for the text model
    cache: KVCache | None  # None when generating by recomputing the window
    done: torch.Tensor  # (B,) done probability of the latest frame
    features: torch.Tensor  # (B, C) the latest frame's final hidden state, averaged over its tokens
    frames_seen: int = 0

    @classmethod
    @torch.no_grad()
    def start(cls, model: nn.Module, prompt_BPS, control: Control, use_cache: bool = True) -> "Rollout":
        """Read the prompt frames (real tokens) with their controls."""
        hidden_BTSC, kvs = model.compute_hidden(prompt_BPS, control)
        cache = KVCache(kvs, model.config.window) if use_cache else None
        done = torch.sigmoid(model.done_logits(hidden_BTSC[:, -1:])[:, 0].float())
        rollout = cls(model, prompt_BPS, control, cache, done, hidden_BTSC[:, -1].mean(dim=1), prompt_BPS.shape[1])
        rollout.slide()
        return rollout

    @torch.no_grad()
    def predict_next_frame(
        self, control: Control, temperature: float = 0.0, generator: torch.Generator | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Generate the next frame under `control` ((B, 1, L, C)) in `maskgit_steps` parallel decoding steps, each
        keeping the most confident of the tokens still masked, then observe it. Returns tokens (B, S) and done (B,)."""
        config = self.model.config
        B, S = self.tokens.shape[0], config.tokens_per_frame
        frame_B1S = torch.full((B, 1, S), config.mask_token_id, dtype=torch.long, device=self.tokens.device)
        known_BS = torch.zeros(B, S, dtype=torch.bool, device=frame_B1S.device)
        steps = config.maskgit_steps
        for step in range(1, steps + 1):
            logits_BSV = self._logits_of_new_frame(frame_B1S, control).float()
            if temperature > 0:
                uniform = torch.rand(logits_BSV.shape, generator=generator, device=logits_BSV.device)
                sample_BS = (logits_BSV / temperature - torch.log(-torch.log(uniform))).argmax(-1)
            else:
                sample_BS = logits_BSV.argmax(-1)
            if step == steps:  # the last step keeps every token still masked
                frame_B1S[:, 0] = torch.where(known_BS, frame_B1S[:, 0], sample_BS)
                break
            confidence_BS = logits_BSV.softmax(-1).gather(-1, sample_BS[..., None]).squeeze(-1)
            n_known = max(int(S * (1 - math.cos(math.pi / 2 * step / steps))), 1)
            keep_BS = known_BS.scatter(1, confidence_BS.masked_fill(known_BS, math.inf).topk(n_known).indices, True)
            frame_B1S[:, 0] = torch.where(keep_BS & ~known_BS, sample_BS, frame_B1S[:, 0])
            known_BS = keep_BS
        return frame_B1S[:, 0], self.observe(frame_B1S, control)

    @torch.no_grad()
    def observe(self, frame_B1S, control: Control) -> torch.Tensor:
        """Append a known frame (generated, or real for teacher forcing) to the rollout; returns its done (B,)."""
        model = self.model
        if self.cache is not None:
            hidden_BTSC, _ = model.compute_hidden(frame_B1S, control, self.cache)
            self.cache.commit()
        else:
            tokens = torch.cat([self.tokens, frame_B1S], 1)
            hidden_BTSC, _ = model.compute_hidden(tokens, self._concat_controls(self.control, control))
        self.features = hidden_BTSC[:, -1].mean(dim=1)
        self.done = torch.sigmoid(model.done_logits(hidden_BTSC[:, -1:])[:, 0].float())
        self.tokens = torch.cat([self.tokens, frame_B1S], 1)
        self.control = self._concat_controls(self.control, control)
        self.frames_seen += 1
        self.slide()
        return self.done

    def slide(self) -> None:
        """Keep the last window - 1 frames: with the new one, a generated frame sees `window` frames."""
        keep = self.model.config.window - 1
        self.tokens = self.tokens[:, -keep:]
        if self.model.config.control == "action":
            self.control = Control(self.control.tokens[:, -keep:], None)

    def _logits_of_new_frame(self, frame_B1S, control: Control) -> torch.Tensor:
        """Logits (B, S, V) of the frame being generated."""
        if self.cache is not None:
            return self.model.compute_logits(frame_B1S, control, self.cache)[0][:, -1]
        # Without the cache: recompute the whole window (past frames + the new one), as the paper's code did.
        tokens = torch.cat([self.tokens, frame_B1S], 1)
        return self.model.compute_logits(tokens, self._concat_controls(self.control, control))[0][:, -1]

    def _concat_controls(self, past: Control, new: Control) -> Control:
        if self.model.config.control == "text":
            return past  # one instruction for every frame
        return Control(torch.cat([past.tokens, new.tokens], 1), None)
