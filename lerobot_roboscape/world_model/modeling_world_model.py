"""STWorldModel: next-frame token prediction (MaskGIT-style) and a done head, conditioned on actions or text.

A model frame stands for k = `frame_skip` control steps. Frame t is conditioned on the control that led to it: for
the action model, the k actions taken from frame t - 1; for the text model, the instruction. Tokens are (B, T, S)
integer grids flattened per frame (views side by side). Generation takes actions one per control step, k per frame.
"""

import math
from pathlib import Path

import torch
import torch.nn.functional as F
from huggingface_hub import snapshot_download
from torch import nn

from lerobot_roboscape.io.weights import CheckedHubMixin
from lerobot_roboscape.world_model.configuration_world_model import WorldModelConfig
from lerobot_roboscape.world_model.control_encoders import ACTION_TOKENS, ActionEncoder, Control, TextEncoder
from lerobot_roboscape.world_model.rollout import Rollout
from lerobot_roboscape.world_model.st_transformer import KVCache, STBlock
from roboscape_core.errors import InvalidInputError

TEXT_ENCODER_DIR = "text_encoder"


def balanced_bce(logits: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
    """Binary cross-entropy with each class averaged on its own, then the two averaged: a rare positive class
    weighs as much as the common negative one (a class absent from the batch drops out). Written with weights, not
    boolean indexing, so that it never waits on the device (no data-dependent shapes)."""
    per_item = F.binary_cross_entropy_with_logits(logits, labels, reduction="none")
    positive = (labels > 0.5).to(per_item.dtype)
    means, present = [], []
    for weight in (positive, 1 - positive):
        count = weight.sum()
        means.append((per_item * weight).sum() / count.clamp(min=1))
        present.append((count > 0).to(per_item.dtype))
    return (means[0] * present[0] + means[1] * present[1]) / (present[0] + present[1]).clamp(min=1)


class STWorldModel(
    nn.Module, CheckedHubMixin, library_name="lerobot-roboscape", tags=["lerobot", "world-model", "robotics"]
):
    def __init__(self, config: WorldModelConfig, text_encoder_dir: str | None = None):
        super().__init__()
        self.config = config
        C, S = config.d_model, config.tokens_per_frame
        self.token_emb = nn.Embedding(config.vocab_size + 1, C)  # + the mask token
        self.pos_emb = nn.Parameter(torch.zeros(S, C))
        if config.control == "action":
            self.control_encoder = ActionEncoder(config)
        else:
            self.control_encoder = TextEncoder(config, saved_dir=text_encoder_dir)
        # The pooled control the blocks' adaptive LayerNorm reads, normalised like the tokens the cross-attention reads
        self.ln_pooled = nn.LayerNorm(C) if config.normalize_control else nn.Identity()
        self.blocks = nn.ModuleList(STBlock(config) for _ in range(config.n_layer))
        self.ln_f = nn.LayerNorm(C)
        self.head = nn.Linear(C, config.vocab_size)
        self.done_head = nn.Sequential(nn.Linear(C, config.done_hidden), nn.GELU(), nn.Linear(config.done_hidden, 1))
        for name, module in self.named_modules():
            if not name.startswith("control_encoder.t5"):
                self._init_weights(module)
        nn.init.normal_(self.pos_emb, std=0.02)
        for block in self.blocks:
            block.zero_init_modulation()
        self._compiled_blocks: list | None = None  # see compile()

    @staticmethod
    def _init_weights(module):
        if isinstance(module, (nn.Linear, nn.Embedding)):
            nn.init.normal_(module.weight, std=0.02)
        if isinstance(module, nn.Linear) and module.bias is not None:
            nn.init.zeros_(module.bias)

    def redraw_top(self, n_blocks: int) -> nn.ModuleList:
        """Draw the last `n_blocks` blocks and everything that reads them (the final norm, the token and done heads)
        afresh, as __init__ draws them (from torch's current seed), and leave them alone trainable: the rest is
        frozen. Returns them."""
        if not 1 <= n_blocks <= len(self.blocks):
            raise InvalidInputError(f"the model has {len(self.blocks)} blocks; cannot take the last {n_blocks}")
        top = nn.ModuleList([*self.blocks[-n_blocks:], self.ln_f, self.head, self.done_head])
        for module in top.modules():
            self._init_weights(module)
            if isinstance(module, nn.LayerNorm):
                module.reset_parameters()
        for module in top.modules():  # after the normal draw, which visits a block before its layers
            if isinstance(module, STBlock):
                module.zero_init_modulation()
        self.requires_grad_(False)
        return top.requires_grad_(True)

    # ---- control -------------------------------------------------------------------------------------------

    def encode_control(self, actions=None, no_action=None, instructions=None) -> Control:
        """Action model: actions (B, T, k, action_dim), the k actions leading to each frame, no_action (B, T) bool.
        Text model: instructions, B strings."""
        if self.config.control == "action":
            if actions is None:
                raise ValueError("the action world model needs actions")
            return self.control_encoder(actions, no_action)
        if instructions is None:
            raise ValueError("the text world model needs instructions")
        return self.control_encoder(instructions)

    def null_control(self, like: Control) -> Control:
        """The learned null control (no action, no instruction) in the shapes of `like`."""
        return self.control_encoder.null_control(like)

    # ---- the network ---------------------------------------------------------------------------------------

    def compute_hidden(self, tokens_BTS, control: Control, cache: KVCache | None = None, fill: KVCache | None = None):
        """Final hidden states (B, T, S, C) and the frames' keys/values per layer. With a cache, T = 1 and the new
        frame's keys/values are written into it instead; with `fill` (an empty cache), the frames' are written into
        that cache, block by block, and none is returned."""
        B, T, S = tokens_BTS.shape
        if self.config.tokens_per_frame != S:
            raise ValueError(f"frames must have {self.config.tokens_per_frame} tokens, got {S}")
        x_BTSC = self.token_emb(tokens_BTS) + self.pos_emb
        control = control._replace(pooled=self.ln_pooled(control.pooled))
        layer_caches = cache.layers if cache is not None else [None] * len(self.blocks)
        blocks = self._compiled_blocks if cache is None and self.training and self._compiled_blocks else self.blocks
        kvs = []
        for i, (block, layer_cache) in enumerate(zip(blocks, layer_caches, strict=True)):
            x_BTSC, kv = block(x_BTSC, control, layer_cache)
            if fill is not None:
                fill.fill(i, *kv)
                kv = None
            kvs.append(kv)
        return self.ln_f(x_BTSC), kvs

    def cache_bytes(self, batch: int, dtype: torch.dtype = torch.float32) -> int:
        """Bytes of the key/value cache a rollout of `batch` samples holds in `dtype` (guided: twice the samples),
        the memory a generation needs beyond the weights and one frame's activations."""
        rows = batch * (2 if self.config.guidance_scale != 1 else 1) * self.config.tokens_per_frame
        itemsize = torch.finfo(dtype).bits // 8
        return KVCache.nbytes(self.config.n_layer, rows, self.config.d_model, self.config.window, itemsize)

    def compute_logits(self, tokens_BTS, control: Control, cache: KVCache | None = None):
        """Logits (B, T, S, V) of every token, done logits (B, T), and the keys/values of `compute_hidden`."""
        hidden_BTSC, kvs = self.compute_hidden(tokens_BTS, control, cache)
        return self.head(hidden_BTSC), self.done_logits(hidden_BTSC), kvs

    def done_logits(self, hidden_BTSC) -> torch.Tensor:
        """The done head reads the whole current frame: (B, T, S, C) -> (B, T)."""
        return self.done_head(hidden_BTSC.mean(dim=2)).squeeze(-1)

    def compute_loss(self, batch: dict) -> tuple[torch.Tensor, dict]:
        """batch: tokens (B, T, S) long, done (B, T) float, and actions (B, T, k, A) + no_action (B, T) or task (B
        strings). Frames after the first are masked at a MaskGIT ratio each, or left clean with clean_frame_prob;
        controls are replaced by the null control with control_dropout. Masked tokens that changed since the
        previous frame weigh changed_weight in the token loss."""
        tokens, done = batch["tokens"], batch["done"]
        B, T, S = tokens.shape
        control = self.encode_control(batch.get("actions"), batch.get("no_action"), batch.get("task"))
        if self.config.control_dropout > 0:
            dropped = torch.rand(control.pooled.shape[:2], device=tokens.device) < self.config.control_dropout
            control = control.where(dropped, self.null_control(control))
        ratio = torch.cos(math.pi / 2 * torch.rand(B, T, 1, device=tokens.device))  # MaskGIT cosine schedule
        ratio = ratio * (torch.rand(B, T, 1, device=tokens.device) >= self.config.clean_frame_prob)
        ratio[:, 0] = 0.0  # the first frame is the prompt
        mask = torch.rand(B, T, S, device=tokens.device) < ratio
        inputs = tokens.masked_fill(mask, self.config.mask_token_id)

        logits, done_logits, _ = self.compute_logits(inputs, control)
        # Every token's loss, weighted: 0 where not masked, changed_weight where masked and changed since the previous
        # frame. No boolean indexing, so a training step never waits on the device.
        changed = torch.zeros_like(mask)
        changed[:, 1:] = tokens[:, 1:] != tokens[:, :-1]
        masked, masked_changed = mask.float(), (mask & changed).float()
        weight = masked + (self.config.changed_weight - 1) * masked_changed
        token_ce = F.cross_entropy(logits.flatten(0, 2).float(), tokens.flatten(), reduction="none").view_as(weight)
        token_loss = (weight * token_ce).sum() / weight.sum().clamp(min=1e-6)
        done_loss = self.done_loss(done_logits.float(), done)
        loss = token_loss + self.config.done_weight * done_loss
        hits = (logits.argmax(-1) == tokens).float()
        n_masked, n_changed = masked.sum(), masked_changed.sum()
        accuracy = (hits * masked).sum() / n_masked.clamp(min=1)
        # the accuracy on the changed tokens: copying the previous frame scores 0 there
        changed_accuracy = torch.where(n_changed > 0, (hits * masked_changed).sum() / n_changed.clamp(min=1), accuracy)
        # Detached tensors: the training loop reads them on its logging steps only.
        logs = {
            "loss": loss,
            "token_ce": token_loss,
            "token_acc": accuracy,
            "changed_acc": changed_accuracy,
            "done_loss": done_loss,
        }
        return loss, {name: value.detach() for name, value in logs.items()}

    def done_loss(self, logits: torch.Tensor, done: torch.Tensor) -> torch.Tensor:
        if self.config.done_loss == "rmse":
            return torch.sqrt(F.mse_loss(torch.sigmoid(logits), done) + 1e-8)
        return balanced_bce(logits, done)

    def forward(self, batch: dict) -> tuple[torch.Tensor, dict]:
        return self.compute_loss(batch)

    def compile(self, **kwargs) -> None:
        """torch.compile the blocks' training pass: regional compilation, tensors in (whatever the control), so one
        graph serves every block and compiles in seconds. Generation, which carries a cache of Python state, stays
        eager, as does the loss around the blocks. The state dict is unchanged."""
        self._compiled_blocks = [torch.compile(block, **kwargs) for block in self.blocks]

    def forward_flops_per_clip(self) -> float:
        """Matmul FLOPs (2 per multiply-add) of the forward pass over one training clip of `window` frames, attention
        included, as nanoGPT's estimate_mfu counts them; a training step costs 3x (the backward pass twice the
        forward's). The frozen T5 is left out: its states are computed once per instruction."""
        c = self.config
        T, S, C, V = c.window, c.tokens_per_frame, c.d_model, c.vocab_size
        L = ACTION_TOKENS if c.control == "action" else c.text_max_length
        per_token = 8 * C * C + 8 * C * C + 4 * C * C + 4 * c.mlp_ratio * C * C  # spatial, temporal, cross, MLP
        attention = T * 4 * S * S * C + S * 4 * T * T * C + T * 4 * S * L * C  # spatial, temporal, cross
        modulated = T if c.control == "action" else 1  # the text's pooled control is one per clip
        modulation = modulated * 24 * C * C if c.adaln != "none" else 0
        blocks = c.n_layer * (T * S * per_token + attention + T * 4 * C * C * L + modulation)  # + cross keys/values
        head = T * S * 2 * C * V + T * 2 * (C * c.done_hidden + c.done_hidden)
        if c.control == "action":
            control = T * 2 * (c.frame_skip * c.action_dim * C + C * ACTION_TOKENS * C)
        else:
            control = 2 * L * self.control_encoder.t5.config.d_model * C  # the projection of the T5 states
        return float(blocks + head + control)

    def training_flops_per_clip(self) -> float:
        return 3 * self.forward_flops_per_clip()

    # ---- generation ----------------------------------------------------------------------------------------

    @torch.no_grad()
    def generate(
        self,
        prompt_BPS,
        n_frames: int,
        actions=None,
        no_action=None,
        instructions=None,
        use_cache: bool = True,
        temperature: float = 0.0,
        generator=None,
        capture: bool = False,
    ):
        """Open-loop generation of `n_frames` frames after the prompt (`capture`: each frame replayed as a CUDA
        graph, world_model/rollout.py).

        Action model: `actions` (B, (P + n_frames - 1) * k, A), one per control step, are the actions taken from the
        prompt frames and from each generated frame but the last (the control of frame t is the k actions from
        frame t - 1); `no_action` (B, P + n_frames - 1) flags frames without one.
        Returns tokens (B, n_frames, S) and done probabilities (B, n_frames).
        """
        P, k = prompt_BPS.shape[1], self.config.frame_skip
        if self.config.control == "action" and (actions is None or actions.shape[1] != (P + n_frames - 1) * k):
            got = None if actions is None else tuple(actions.shape)
            raise ValueError(
                f"need {(P + n_frames - 1) * k} actions ({k} per frame) for {P} prompt and {n_frames} new frames, "
                f"got {got}"
            )
        control = self.episode_control(actions, no_action, instructions)
        rollout = Rollout.start(self, prompt_BPS, control.frames(slice(0, P)), use_cache, guided=True, capture=capture)
        frames, dones = [], []
        for t in range(P, P + n_frames):
            frame, done = rollout.predict_next_frame(control.frames(slice(t, t + 1)), temperature, generator)
            frames.append(frame)
            dones.append(done)
        return torch.stack(frames, 1), torch.stack(dones, 1)

    @torch.no_grad()
    def teacher_forced(self, tokens_BTS, actions=None, instructions=None) -> tuple[torch.Tensor, torch.Tensor]:
        """Read known frames one after the other, as a rollout would (each sees the window before it). Returns
        done probabilities (B, T) and features (B, T, C). Actions: (B, (T - 1) * k, A), actions t * k .. t * k + k - 1
        leading to frame t + 1."""
        control = self.episode_control(actions, instructions=instructions)
        rollout = Rollout.start(self, tokens_BTS[:, :1], control.frames(slice(0, 1)))
        done, features = [rollout.done], [rollout.features]
        for t in range(1, tokens_BTS.shape[1]):
            done.append(rollout.observe(tokens_BTS[:, t : t + 1], control.frames(slice(t, t + 1))))
            features.append(rollout.features)
        return torch.stack(done, 1), torch.stack(features, 1)

    def episode_control(self, actions=None, no_action=None, instructions=None) -> Control:
        """Controls of an episode's frames from its actions (B, (T - 1) * k, A), one per control step, chunk t leading
        to frame t + 1 (frame 0 has none), or from its instructions (one control shared by all frames)."""
        if self.config.control == "text":
            return self.encode_control(instructions=instructions)
        B, N, A = actions.shape
        k = self.config.frame_skip
        if N % k:
            raise ValueError(f"{N} actions do not make whole frames of frame_skip={k} actions")
        chunks = actions.reshape(B, N // k, k, A)
        shifted = torch.cat([chunks.new_zeros(B, 1, k, A), chunks], 1)
        flags = torch.zeros(shifted.shape[:2], dtype=torch.bool, device=shifted.device)
        flags[:, 0] = True
        if no_action is not None:
            flags[:, 1:] |= no_action
        return self.encode_control(shifted, flags)

    # ---- saving --------------------------------------------------------------------------------------------

    def _save_pretrained(self, save_directory: Path) -> None:
        super()._save_pretrained(save_directory)
        if self.config.control == "text":
            self.control_encoder.save_tokenizer_and_config(Path(save_directory) / TEXT_ENCODER_DIR)

    @classmethod
    def _from_pretrained(
        cls,
        *,
        model_id: str,
        revision=None,
        cache_dir=None,
        force_download=False,
        local_files_only=False,
        token=None,
        **kwargs,
    ):
        # A text model rebuilds its T5 from the saved config and tokenizer (weights come with the world model's).
        if Path(model_id).is_dir():
            root = Path(model_id)
        else:
            root = Path(
                snapshot_download(
                    model_id,
                    revision=revision,
                    cache_dir=cache_dir,
                    token=token,
                    local_files_only=local_files_only,
                    allow_patterns=[f"{TEXT_ENCODER_DIR}/*"],
                )
            )
        if (root / TEXT_ENCODER_DIR).is_dir():
            kwargs["text_encoder_dir"] = str(root / TEXT_ENCODER_DIR)
        model = super()._from_pretrained(
            model_id=model_id,
            revision=revision,
            cache_dir=cache_dir,
            force_download=force_download,
            local_files_only=local_files_only,
            token=token,
            **kwargs,
        )
        if model.config.control == "action" and model.config.action_mean is None:
            zeros, ones = [0.0] * model.config.action_dim, [1.0] * model.config.action_dim
            raise InvalidInputError(
                f"{model_id}: an action world model saved without action statistics (before actions were "
                "normalised); retrain it with roboscape-train-wm, or keep its raw-action behaviour by adding "
                f'"action_mean": {zeros}, "action_std": {ones} to its config.json'
            )
        return model
