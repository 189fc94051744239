"""Control encoders: what the world model reads of its control. Both return `Control`: tokens for the cross-attention
and one pooled vector per frame for the blocks' adaptive LayerNorm, and a null control of the same shapes (the
unconditional mode that control dropout trains and classifier-free guidance subtracts)."""

from pathlib import Path
from typing import NamedTuple

import torch
from torch import nn
from transformers import AutoTokenizer, ByT5Tokenizer, T5Config, T5EncoderModel

from lerobot_roboscape.world_model.configuration_world_model import WorldModelConfig

# Several tokens per action let each image token's query pick its own mix of the action's features.
ACTION_TOKENS = 4
# Planned rotations barely move (std ~1e-3): a policy's exploratory 0.1 rad would read as 100 std without a floor.
ACTION_STD_FLOOR = 0.05
TINY_T5 = dict(d_model=64, d_kv=16, d_ff=128, num_layers=2, num_heads=4, dropout_rate=0.0)


class Control(NamedTuple):
    tokens: torch.Tensor  # (B, T, L, C), or (B, 1, L, C) when every frame shares it (text)
    mask: torch.Tensor | None  # (B, T or 1, L) bool, True where a token may be attended to; None = all
    pooled: torch.Tensor  # (B, T or 1, C): what the adaptive LayerNorm of every block reads

    def frames(self, frames: slice) -> "Control":
        """The controls of some frames; a control shared by every frame (text) is returned whole."""
        if self.tokens.shape[1] == 1:
            return self
        return Control(
            self.tokens[:, frames], None if self.mask is None else self.mask[:, frames], self.pooled[:, frames]
        )

    def where(self, use_null: torch.Tensor, null: "Control") -> "Control":
        """This control with the null one where `use_null` ((B, T or 1) bool) is set."""
        tokens = torch.where(use_null[..., None, None], null.tokens, self.tokens)
        mask = None if self.mask is None else torch.where(use_null[..., None], null.mask, self.mask)
        return Control(tokens, mask, torch.where(use_null[..., None], null.pooled, self.pooled))

    def with_context(self, extra_B1MC: torch.Tensor) -> "Control":
        """This control with M more cross-attention tokens, shared by every frame and always attended to (the
        anchor frame's positions); the pooled control, which the adaptive LayerNorm reads, stays the control's."""
        B, T = self.tokens.shape[:2]
        tokens = torch.cat([self.tokens, extra_B1MC.to(self.tokens.dtype).expand(B, T, -1, -1)], 2)
        mask = self.mask
        if mask is not None:
            mask = torch.cat([mask, mask.new_ones(*mask.shape[:2], extra_B1MC.shape[2])], 2)
        return Control(tokens, mask, self.pooled)

    @staticmethod
    def cat(controls: list["Control"], dim: int) -> "Control":
        masks = [c.mask for c in controls]
        mask = None if masks[0] is None else torch.cat(masks, dim)
        return Control(torch.cat([c.tokens for c in controls], dim), mask, torch.cat([c.pooled for c in controls], dim))


class ActionEncoder(nn.Module):
    """A frame's chunk of k 7-D actions, normalised by the training data's statistics -> ACTION_TOKENS tokens per
    frame. Frames with no preceding action (an episode's first frame) get a learned null action.

    Every caller (training, generation, the reports, `roboscape_wm`) passes raw actions: the normalisation lives
    here only, with the statistics saved in the model's config."""

    def __init__(self, config: WorldModelConfig):
        super().__init__()
        self.action_dim, self.frame_skip, self.d_model = config.action_dim, config.frame_skip, config.d_model
        mean = torch.zeros(config.action_dim) if config.action_mean is None else torch.tensor(config.action_mean)
        std = torch.ones(config.action_dim) if config.action_std is None else torch.tensor(config.action_std)
        self.register_buffer("mean", mean.float(), persistent=False)
        self.register_buffer("std", std.float().clamp(min=ACTION_STD_FLOOR), persistent=False)
        self.mlp = nn.Sequential(
            nn.Linear(config.frame_skip * config.action_dim, config.d_model),
            nn.GELU(),
            nn.Linear(config.d_model, ACTION_TOKENS * config.d_model),
        )
        self.null = nn.Parameter(torch.zeros(ACTION_TOKENS * config.d_model))

    def forward(self, actions: torch.Tensor, no_action: torch.Tensor | None = None) -> Control:
        """actions: (B, T, k, action_dim) float, the k actions leading to each frame; no_action: (B, T) bool."""
        if actions.ndim != 4 or actions.shape[-2:] != (self.frame_skip, self.action_dim):
            raise ValueError(
                f"actions must have shape (B, T, {self.frame_skip}, {self.action_dim}) (k = frame_skip actions per "
                f"frame), got {tuple(actions.shape)}"
            )
        normalised = (actions - self.mean.to(actions.dtype)) / self.std.to(actions.dtype)
        emb = self.mlp(normalised.flatten(-2))
        if no_action is not None:
            emb = torch.where(no_action[..., None], self.null.to(emb.dtype), emb)
        return self._control(emb)

    def null_control(self, like: Control) -> Control:
        """The null action in every frame of `like`."""
        return self._control(self.null.to(like.tokens.dtype).expand(*like.tokens.shape[:2], -1))

    def _control(self, emb_BTX: torch.Tensor) -> Control:
        tokens = emb_BTX.unflatten(-1, (ACTION_TOKENS, self.d_model))
        return Control(tokens, None, tokens.mean(dim=2))


class TextEncoder(nn.Module):
    """Instruction -> T5 encoder states -> d_model tokens. T5 stays frozen; its outputs are cached per string."""

    def __init__(self, config: WorldModelConfig, saved_dir: str | Path | None = None):
        super().__init__()
        self.max_length = config.text_max_length
        if saved_dir is not None:  # rebuilt from a saved world model; its weights come with the world model's
            self.tokenizer = AutoTokenizer.from_pretrained(saved_dir)
            self.t5 = T5EncoderModel(T5Config.from_pretrained(saved_dir))
        elif config.text_encoder is not None:
            self.tokenizer = AutoTokenizer.from_pretrained(config.text_encoder)
            self.t5 = T5EncoderModel.from_pretrained(config.text_encoder)
        else:
            self.tokenizer = ByT5Tokenizer()
            self.t5 = T5EncoderModel(T5Config(vocab_size=len(self.tokenizer), **TINY_T5))
        self.t5.requires_grad_(False).eval()
        self.proj = nn.Linear(self.t5.config.d_model, config.d_model)
        self.null = nn.Parameter(torch.zeros(config.d_model))  # the "no instruction" token
        self._cache: dict[str, tuple[torch.Tensor, torch.Tensor]] = {}

    def train(self, mode: bool = True):
        super().train(mode)
        self.t5.eval()  # frozen: no dropout, ever
        return self

    @torch.no_grad()
    def _t5_states(self, instructions: list[str], device) -> tuple[torch.Tensor, torch.Tensor]:
        missing = sorted({s for s in instructions if s not in self._cache})
        if missing:
            batch = self.tokenizer(
                missing, padding="max_length", max_length=self.max_length, truncation=True, return_tensors="pt"
            ).to(device)
            states = self.t5(**batch).last_hidden_state.float()
            for i, s in enumerate(missing):
                self._cache[s] = (states[i], batch["attention_mask"][i].bool())
        states, mask = zip(*(self._cache[s] for s in instructions), strict=True)
        return torch.stack(states).to(device), torch.stack(mask).to(device)

    def forward(self, instructions: list[str]) -> Control:
        if not instructions or not all(isinstance(s, str) and s for s in instructions):
            raise ValueError(f"instructions must be non-empty strings, got {instructions!r}")
        states, mask = self._t5_states(list(instructions), self.proj.weight.device)
        tokens = self.proj(states.to(self.proj.weight.dtype))  # (B, L, C)
        pooled = (tokens * mask[..., None]).sum(1) / mask.sum(1, keepdim=True).clamp(min=1)
        return Control(tokens[:, None], mask[:, None], pooled[:, None])

    def null_control(self, like: Control) -> Control:
        """The null instruction: one attended token, the same for every sample."""
        B, T, L, C = like.tokens.shape
        mask = torch.zeros(B, T, L, dtype=torch.bool, device=like.tokens.device)
        mask[..., 0] = True
        null = self.null.to(like.tokens.dtype)
        return Control(null.expand(B, T, L, C), mask, null.expand(B, T, C))

    def save_tokenizer_and_config(self, directory: str | Path) -> None:
        self.tokenizer.save_pretrained(directory)
        self.t5.config.save_pretrained(directory)
