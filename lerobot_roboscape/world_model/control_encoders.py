"""Control encoders: what the world model's cross-attention reads. Both return `Control` tokens, one set per frame."""

from pathlib import Path
from typing import NamedTuple

import torch
from torch import nn
from transformers import AutoTokenizer, ByT5Tokenizer, T5Config, T5EncoderModel

from lerobot_roboscape.world_model.configuration_world_model import WorldModelConfig

# Several tokens per action let each image token's query pick its own mix of the action's features.
ACTION_TOKENS = 4
TINY_T5 = dict(d_model=64, d_kv=16, d_ff=128, num_layers=2, num_heads=4, dropout_rate=0.0)


class Control(NamedTuple):
    tokens: torch.Tensor  # (B, T, L, C), or (B, 1, L, C) when every frame shares it (text)
    mask: torch.Tensor | None  # (B, T or 1, L) bool, True where a token may be attended to; None = all


class ActionEncoder(nn.Module):
    """7-D actions -> ACTION_TOKENS tokens per frame. Frames with no preceding action (an episode's first frame)
    get a learned null action."""

    def __init__(self, config: WorldModelConfig):
        super().__init__()
        self.action_dim, self.d_model = config.action_dim, config.d_model
        self.mlp = nn.Sequential(
            nn.Linear(config.action_dim, config.d_model),
            nn.GELU(),
            nn.Linear(config.d_model, ACTION_TOKENS * config.d_model),
        )
        self.null = nn.Parameter(torch.zeros(ACTION_TOKENS * config.d_model))

    def forward(self, actions: torch.Tensor, no_action: torch.Tensor | None = None) -> Control:
        """actions: (B, T, action_dim) float; no_action: (B, T) bool."""
        if actions.ndim != 3 or actions.shape[-1] != self.action_dim:
            raise ValueError(f"actions must have shape (B, T, {self.action_dim}), got {tuple(actions.shape)}")
        emb = self.mlp(actions)
        if no_action is not None:
            emb = torch.where(no_action[..., None], self.null.to(emb.dtype), emb)
        return Control(emb.unflatten(-1, (ACTION_TOKENS, self.d_model)), None)


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
        return Control(self.proj(states.to(self.proj.weight.dtype))[:, None], mask[:, None])

    def save_tokenizer_and_config(self, directory: str | Path) -> None:
        self.tokenizer.save_pretrained(directory)
        self.t5.config.save_pretrained(directory)
