"""STWorldModel: next-frame token prediction (MaskGIT-style) and a done head, conditioned on actions or text, with
the robot's state as a channel (world_model/robot_state.py).

A model frame stands for k = `frame_skip` control steps. Frame t is conditioned on the control that led to it: for
the action model, the k actions taken from frame t - 1; for the text model, the instruction. Tokens are (B, T, S)
integer grids flattened per frame (views side by side); inside the model a position holds patch x patch of a view's
codes (N positions of G codes each: `group`), while everything outside reads and writes codes. Generation takes
actions one per control step, k per frame, and states one per frame.
"""

from typing import NamedTuple

import torch
import torch.nn.functional as F
from einops import rearrange
from torch import nn

from lerobot_roboscape.training.losses import balanced_bce
from lerobot_roboscape.world_model.configuration_world_model import WorldModelConfig
from lerobot_roboscape.world_model.control_encoders import ActionEncoder, Control, TextEncoder
from lerobot_roboscape.world_model.flops import forward_flops_per_clip
from lerobot_roboscape.world_model.objective import changed_codes, masked_inputs, masked_token_loss
from lerobot_roboscape.world_model.robot_state import RobotState
from lerobot_roboscape.world_model.rollout import Rollout
from lerobot_roboscape.world_model.saved import SavedWorldModel
from lerobot_roboscape.world_model.st_transformer import KVCache, STBlock
from roboscape_core.errors import InvalidInputError


class Generated(NamedTuple):
    tokens: torch.Tensor  # (B, n_frames, S)
    done: torch.Tensor  # (B, n_frames) probabilities
    state: torch.Tensor | None  # (B, n_frames, state_dim) the predicted raw states; None without a state channel


class STWorldModel(
    nn.Module, SavedWorldModel, library_name="lerobot-roboscape", tags=["lerobot", "world-model", "robotics"]
):
    def __init__(self, config: WorldModelConfig, text_encoder_dir: str | None = None):
        super().__init__()
        self.config = config
        C, N, G = config.d_model, config.positions_per_frame, config.codes_per_position
        # One table per place in a position's patch (+ the mask token each), summed into the position's embedding.
        self.token_emb = nn.Embedding(G * (config.vocab_size + 1), C)
        self.register_buffer("code_offsets", torch.arange(G) * (config.vocab_size + 1), persistent=False)
        self.pos_emb = nn.Parameter(torch.zeros(N, C))
        self.anchor_emb = nn.Parameter(torch.zeros(C)) if config.anchor else None  # marks the anchor's positions
        self.robot_state = RobotState(config) if config.state else None
        if config.control == "action":
            self.control_encoder = ActionEncoder(config)
        else:
            self.control_encoder = TextEncoder(config, saved_dir=text_encoder_dir)
        # The pooled control the blocks' adaptive LayerNorm reads, normalised like the tokens the cross-attention reads
        self.ln_pooled = nn.LayerNorm(C) if config.normalize_control else nn.Identity()
        self.blocks = nn.ModuleList(STBlock(config) for _ in range(config.n_layer))
        self.ln_f = nn.LayerNorm(C)
        self.head = nn.Linear(C, G * config.vocab_size)  # a code's logits per place in the patch
        self.done_head = nn.Sequential(nn.Linear(C, config.done_hidden), nn.GELU(), nn.Linear(config.done_hidden, 1))
        for name, module in self.named_modules():
            if not name.startswith("control_encoder.t5"):
                self._init_weights(module)
        for embedding in (self.pos_emb, self.anchor_emb):
            if embedding is not None:
                nn.init.normal_(embedding, std=0.02)
        for block in self.blocks:
            block.zero_init_modulation()
        if self.robot_state is not None:
            self.robot_state.zero_init_head()
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
        if self.robot_state is not None:
            top.append(self.robot_state.head)
        for module in top.modules():
            self._init_weights(module)
            if isinstance(module, nn.LayerNorm):
                module.reset_parameters()
        for module in top.modules():  # after the normal draw, which visits a block before its layers
            if isinstance(module, STBlock):
                module.zero_init_modulation()
        if self.robot_state is not None:
            self.robot_state.zero_init_head()
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

    def group(self, codes_BTS: torch.Tensor) -> torch.Tensor:
        """(B, T, S, ...) in code order -> (B, T, N, G, ...): each position's patch of codes."""
        c = self.config
        side = c.tokens_per_side // c.patch
        return rearrange(
            codes_BTS, "b t (n h p w q) ... -> b t (n h w) (p q) ...", n=c.n_cameras, h=side, w=side, p=c.patch
        )

    def ungroup(self, grouped_BTNG: torch.Tensor) -> torch.Tensor:
        """(B, T, N, G, ...) -> (B, T, S, ...) in code order: the inverse of `group`."""
        c = self.config
        side = c.tokens_per_side // c.patch
        return rearrange(
            grouped_BTNG, "b t (n h w) (p q) ... -> b t (n h p w q) ...", n=c.n_cameras, h=side, w=side, p=c.patch
        )

    def _pooled(self, control: Control) -> Control:
        """The control whose pooled vector is normalised as the blocks and the state head read it."""
        return control._replace(pooled=self.ln_pooled(control.pooled))

    def embed(self, tokens_BTS) -> torch.Tensor:
        """Each position's embedding (B, T, N, C): its codes' and its place's."""
        return self.token_emb(self.group(tokens_BTS) + self.code_offsets).sum(3) + self.pos_emb

    def _anchored(self, control: Control, tokens_BTS, anchor_BS, cached: bool) -> Control:
        """With `config.anchor`, the control with the anchor frame's positions in its cross-attention: `anchor_BS`,
        else the first of the frames read (a prompt, a clip), which a cached step of one new frame has not."""
        if self.anchor_emb is None:
            return control
        if anchor_BS is None:
            if cached:
                raise ValueError("a cached step of an anchored world model needs its rollout's anchor frame")
            anchor_BS = tokens_BTS[:, 0]
        return control.with_context(self.embed(anchor_BS[:, None]) + self.anchor_emb)

    def compute_hidden(
        self,
        tokens_BTS,
        control: Control,
        cache: KVCache | None = None,
        fill: KVCache | None = None,
        states: torch.Tensor | None = None,
        anchor: torch.Tensor | None = None,
    ):
        """Final hidden states (B, T, N, C) and the frames' keys/values per layer. With a cache, T = 1 and the new
        frame's keys/values are written into it instead; with `fill` (an empty cache), the frames' are written into
        that cache, block by block, and none is returned. `states`: the frames' raw states (B, T, state_dim), which
        a model with a state channel needs; `anchor`: the episode's first frame (B, S), which an anchored model
        reads (by default the first of `tokens_BTS`)."""
        B, T, S = tokens_BTS.shape
        if self.config.tokens_per_frame != S:
            raise ValueError(f"frames must have {self.config.tokens_per_frame} tokens, got {S}")
        x_BTNC = self.embed(tokens_BTS)
        if self.robot_state is not None:
            if states is None or states.shape[:2] != (B, T):
                got = None if states is None else tuple(states.shape)
                raise ValueError(
                    f"a world model with a state channel needs the frames' states ({B}, {T}, D), got {got}"
                )
            x_BTNC = x_BTNC + self.robot_state.embedding(states).to(x_BTNC.dtype)[:, :, None]
        control = self._anchored(self._pooled(control), tokens_BTS, anchor, cached=cache is not None)
        layer_caches = cache.layers if cache is not None else [None] * len(self.blocks)
        blocks = self._compiled_blocks if cache is None and self.training and self._compiled_blocks else self.blocks
        kvs = []
        for i, (block, layer_cache) in enumerate(zip(blocks, layer_caches, strict=True)):
            x_BTNC, kv = block(x_BTNC, control, layer_cache)
            if fill is not None:
                fill.fill(i, *kv)
                kv = None
            kvs.append(kv)
        return self.ln_f(x_BTNC), kvs

    def cache_bytes(self, batch: int, dtype: torch.dtype = torch.float32) -> int:
        """Bytes of the key/value cache a rollout of `batch` samples holds in `dtype` (guided: twice the samples),
        the memory a generation needs beyond the weights and one frame's activations."""
        rows = batch * (2 if self.config.guidance_scale != 1 else 1) * self.config.positions_per_frame
        itemsize = torch.finfo(dtype).bits // 8
        return KVCache.nbytes(self.config.n_layer, rows, self.config.d_model, self.config.window, itemsize)

    def token_logits(self, hidden_BTNC) -> torch.Tensor:
        """Logits (B, T, S, V) of every code, in code order."""
        B, T, N, _ = hidden_BTNC.shape
        return self.ungroup(self.head(hidden_BTNC).view(B, T, N, self.config.codes_per_position, -1))

    def compute_logits(self, tokens_BTS, control: Control, cache: KVCache | None = None, states=None, anchor=None):
        """Logits (B, T, S, V) of every token, done logits (B, T), and the keys/values of `compute_hidden`."""
        hidden_BTNC, kvs = self.compute_hidden(tokens_BTS, control, cache, states=states, anchor=anchor)
        return self.token_logits(hidden_BTNC), self.done_logits(hidden_BTNC), kvs

    def token_loss(self, hidden_BTNC, tokens_BTS, mask_BTS) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """The masked codes' loss (objective.py), the head reading the masked positions only or every position
        (config.masked_head); a position's codes are masked together."""
        grouped = [self.group(x) for x in (tokens_BTS, mask_BTS, changed_codes(tokens_BTS))]
        select = self.config.masked_head
        if select is None:  # FLOPs are what counts on the CPU; elsewhere, that a step never waits on the device
            select = hidden_BTNC.device.type == "cpu"
        if select:
            rows_BTN = grouped[1][..., 0]
            hidden_RC, grouped = hidden_BTNC[rows_BTN], [x[rows_BTN] for x in grouped]
        else:
            hidden_RC, grouped = hidden_BTNC.flatten(0, 2), [x.flatten(0, 2) for x in grouped]
        G = self.config.codes_per_position
        logits_RGV = self.head(hidden_RC).view(len(hidden_RC), G, self.head.out_features // G)  # R may be 0
        return masked_token_loss(logits_RGV, *grouped, self.config.changed_weight)

    def done_logits(self, hidden_BTNC) -> torch.Tensor:
        """The done head reads the whole current frame: (B, T, N, C) -> (B, T)."""
        return self.done_head(hidden_BTNC.mean(dim=2)).squeeze(-1)

    def predict_state(self, features_BC, state_BD, control: Control) -> torch.Tensor | None:
        """The next frame's raw state (B, D) from this frame's features and state and the next frame's control
        ((B, 1, L, C), or the text's shared one); None without a state channel."""
        if self.robot_state is None:
            return None
        pooled = self._pooled(control).pooled[: len(state_BD), -1]
        return self.robot_state.predict_next(features_BC, state_BD, pooled)

    def compute_loss(self, batch: dict) -> tuple[torch.Tensor, dict]:
        """batch: tokens (B, T, S) long, done (B, T) float, state (B, T, D) with a state channel, anchor (B, S) the
        episode's first frame (an anchored model), and actions (B, T, k, A) + no_action (B, T) or task (B strings).
        Positions of frames after the first are masked at a MaskGIT ratio each, or left clean with clean_frame_prob;
        a share of the codes left unmasked, drawn per clip up to corrupt_max, is replaced by random codes; controls
        are replaced by the null control with control_dropout. Masked tokens that changed since the previous frame
        weigh changed_weight in the token loss; each frame's predicted next state is scored against the clip's next
        frame."""
        tokens, done, c = batch["tokens"], batch["done"], self.config
        control = self.encode_control(batch.get("actions"), batch.get("no_action"), batch.get("task"))
        if c.control_dropout > 0:
            dropped = torch.rand(control.pooled.shape[:2], device=tokens.device) < c.control_dropout
            control = control.where(dropped, self.null_control(control))
        inputs, mask = masked_inputs(tokens, c, self.ungroup)
        states = batch.get("state")
        hidden, _ = self.compute_hidden(inputs, control, states=states, anchor=batch.get("anchor"))
        token_loss, token_logs = self.token_loss(hidden, tokens, mask)
        done_loss = self.done_loss(self.done_logits(hidden).float(), done)
        loss = token_loss + c.done_weight * done_loss
        logs = {"loss": loss, **token_logs, "done_loss": done_loss}  # tensors: the loop reads them when it logs
        if self.robot_state is not None:
            state_loss = self.robot_state.loss(hidden.mean(2), states, self._pooled(control).pooled)
            loss = loss + state_loss
            logs |= {"loss": loss, "state_mse": state_loss}
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
        text_width = self.control_encoder.t5.config.d_model if self.config.control == "text" else None
        return forward_flops_per_clip(self.config, text_width)

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
        states=None,
    ) -> Generated:
        """Open-loop generation of `n_frames` frames after the prompt (`capture`: each frame replayed as a CUDA
        graph, world_model/rollout.py).

        Action model: `actions` (B, (P + n_frames - 1) * k, A), one per control step, are the actions taken from the
        prompt frames and from each generated frame but the last (the control of frame t is the k actions from
        frame t - 1); `no_action` (B, P + n_frames - 1) flags frames without one. `states` (B, P, D): the prompt
        frames' real states (a model with a state channel); every later state is the model's own prediction.
        """
        P, k = prompt_BPS.shape[1], self.config.frame_skip
        if self.config.control == "action" and (actions is None or actions.shape[1] != (P + n_frames - 1) * k):
            got = None if actions is None else tuple(actions.shape)
            raise ValueError(
                f"need {(P + n_frames - 1) * k} actions ({k} per frame) for {P} prompt and {n_frames} new frames, "
                f"got {got}"
            )
        control = self.episode_control(actions, no_action, instructions)
        rollout = Rollout.start(
            self, prompt_BPS, control.frames(slice(0, P)), use_cache, guided=True, capture=capture, states=states
        )
        frames, dones, predicted = [], [], []
        for t in range(P, P + n_frames):
            frame, done = rollout.predict_next_frame(control.frames(slice(t, t + 1)), temperature, generator)
            frames.append(frame)
            dones.append(done)
            predicted.append(rollout.state)
        state = None if rollout.state is None else torch.stack(predicted, 1)
        return Generated(torch.stack(frames, 1), torch.stack(dones, 1), state)

    @torch.no_grad()
    def teacher_forced(
        self, tokens_BTS, actions=None, instructions=None, states=None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Read known frames one after the other, as a rollout would (each sees the window before it). Returns
        done probabilities (B, T) and features (B, T, C). Actions: (B, (T - 1) * k, A), actions t * k .. t * k + k - 1
        leading to frame t + 1; states: the frames' real states (B, T, D) (a model with a state channel)."""
        control = self.episode_control(actions, instructions=instructions)
        first = None if states is None else states[:, :1]
        rollout = Rollout.start(self, tokens_BTS[:, :1], control.frames(slice(0, 1)), states=first)
        done, features = [rollout.done], [rollout.features]
        for t in range(1, tokens_BTS.shape[1]):
            state = None if states is None else states[:, t]
            done.append(rollout.observe(tokens_BTS[:, t : t + 1], control.frames(slice(t, t + 1)), state))
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
