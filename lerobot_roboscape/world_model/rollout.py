"""A running generation of a world model: start from prompt frames, predict the next frame by MaskGIT decoding,
observe known frames, slide the window.

With the key/value cache (the default) a new frame is computed against the cached keys and values of the frames
before it. Without it, every step re-reads the whole window of past frames, as the paper's code (1xgpt's
`STMaskGIT.generate`) does. Both give the same tokens while the rollout fits in the window; past it, a cached frame
keeps the keys and values it was computed with (its own window of context), where recomputing re-reads the oldest
frames of the window without theirs.

With a state channel the rollout carries the robot's state: it starts from the prompt frames' real states, and
before each new frame predicts that frame's state (from the latest frame's features and state and the new frame's
control), under which the frame's tokens are decoded and read; `state` is the latest frame's.

With classifier-free guidance (`guidance_scale` != 1) the rollout runs twice the batch: each sample under its control
and under the null control, each half with its own keys and values, and decodes from the guided logits.

On a GPU a frame is hundreds of small kernels (every block, every MaskGIT step), so at small batches launching them
costs more than running them. With `capture`, a cached rollout on CUDA records one frame's work (the MaskGIT steps,
the commit pass, the cache's move to the next slot) as a CUDA graph and replays it for every later frame: one launch
a frame. The graph belongs to the cache's rings, which a new episode of the same shape reuses (`Rollout.start`'s
`reuse`).
"""

import math
from dataclasses import dataclass

import torch
from torch import nn

from lerobot_roboscape.world_model.control_encoders import Control
from lerobot_roboscape.world_model.st_transformer import KVCache

WARMUP_FRAMES = 2  # eager passes before a capture, on a side stream, so lazy initialisation is not recorded


def readout(model, hidden_BTNC: torch.Tensor, B: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The latest frame's done probability (B,) and pooled features (B, C), from the first B rows (a guided
    rollout's second half is its unconditional twin)."""
    return torch.sigmoid(model.done_logits(hidden_BTNC[:B, -1:])[:, 0].float()), hidden_BTNC[:B, -1].mean(dim=1)


@dataclass
class Rollout:
    """What a running generation remembers: the last `window - 1` frames as tokens, their controls and states, and
    (with the cache) every layer's keys and values of those frames. When guided, tokens, controls, states and cache
    hold the samples under their control followed by the same samples under the null control."""

    model: nn.Module  # an STWorldModel (not imported: it imports this module to generate)
    tokens: torch.Tensor  # (B, T, S) long, (2B, T, S) when guided
    control: Control  # (B, T, L, C) for the action model; (B, 1, L, C) shared for the text model
    cache: KVCache | None  # None when generating by recomputing the window
    done: torch.Tensor  # (B,) done probability of the latest frame
    features: torch.Tensor  # (B, C) the latest frame's final hidden state, averaged over its positions
    states: torch.Tensor | None  # (B, T, D) raw states of the frames, (2B, T, D) when guided; None without a channel
    frames_seen: int = 0
    guided: bool = False
    capture: bool = False
    anchor: torch.Tensor | None = None  # (B, S), (2B, S) when guided: the first prompt frame, for an anchored model

    @classmethod
    @torch.no_grad()
    def start(
        cls,
        model: nn.Module,
        prompt_BPS,
        control: Control,
        use_cache: bool = True,
        guided: bool = True,
        capture: bool = False,
        reuse: "Rollout | None" = None,
        states: torch.Tensor | None = None,
    ) -> "Rollout":
        """Read the prompt frames (real tokens) with their controls and real states ((B, P, D), a model with a state
        channel). `guided`: apply the model's guidance scale (reading known frames only, as teacher forcing does,
        needs no guidance). `capture`: replay each frame's work as a CUDA graph (a cached rollout on CUDA). `reuse`:
        an earlier rollout of the same model whose cache (and the graphs captured against it) this one refills when
        the shapes match."""
        if capture and (not use_cache or prompt_BPS.device.type != "cuda"):
            raise ValueError(
                f"capture needs the key/value cache on a CUDA device (use_cache={use_cache}, "
                f"device {prompt_BPS.device})"
            )
        guided = guided and model.config.guidance_scale != 1
        B = prompt_BPS.shape[0]
        if not model.config.state:
            states = None
        elif states is None:
            raise ValueError("a world model with a state channel starts a rollout from its prompt frames' states")
        if guided:
            prompt_BPS = torch.cat([prompt_BPS, prompt_BPS])
            control = Control.cat([control, model.null_control(control)], 0)
            states = None if states is None else torch.cat([states, states])
        cache = None
        if use_cache:
            reusable = reuse is not None and reuse.cache is not None and reuse.model is model
            cache = reuse.cache if reusable else KVCache(model.config.n_layer, model.config.window)
        anchor = prompt_BPS[:, 0] if model.config.anchor else None
        hidden_BTNC, _ = model.compute_hidden(prompt_BPS, control, fill=cache, states=states, anchor=anchor)
        done, features = readout(model, hidden_BTNC, B)
        rollout = cls(
            model, prompt_BPS, control, cache, done, features, states, prompt_BPS.shape[1], guided, capture, anchor
        )
        rollout.slide()
        return rollout

    @property
    def state(self) -> torch.Tensor | None:
        """The latest frame's raw state (B, D): real for the prompt and observed frames, predicted for generated
        ones; None without a state channel."""
        return None if self.states is None else self.states[: self.done.shape[0], -1]

    @torch.no_grad()
    def predict_next_frame(
        self, control: Control, temperature: float = 0.0, generator: torch.Generator | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Generate the next frame under `control` ((B, 1, L, C)) in `maskgit_steps` parallel decoding steps, each
        keeping the most confident of the tokens still masked, then observe it. Returns
        tokens (B, S) and done (B,)."""
        control = self._paired(control)
        if self.capture:
            frame_B1S, done, features, state = self._replay(control, temperature, generator)
        else:
            frame_B1S, done, features, state = self._frame(control, temperature, generator)
            if self.cache is not None:
                self.cache.commit()
        self._remember(frame_B1S, control, done, features, state)
        return frame_B1S[:, 0], done

    def _frame(self, control: Control, temperature: float, generator) -> tuple:
        """The next frame's predicted state, its tokens decoded under it, then its done and features."""
        state = self._next_state(control)
        frame_B1S = self._decode(control, state, temperature, generator)
        return frame_B1S, *self._read(frame_B1S, control, state), state

    def _next_state(self, control: Control) -> torch.Tensor | None:
        """The next frame's states (B, 1, D), paired when guided: predicted under the frame's own control."""
        if self.states is None:
            return None
        state = self.model.predict_state(self.features, self.state, control)[:, None]
        return torch.cat([state, state]) if self.guided else state

    @torch.no_grad()
    def next_frame_logits(self, control: Control) -> torch.Tensor:
        """Logits (B, S, V) of the next frame under `control` ((B, 1, L, C)) before any of its tokens is decoded
        (MaskGIT's first pass): the model's prediction of every token, which an ensemble compares. The rollout is
        left as it was."""
        config = self.model.config
        B = self.done.shape[0]
        masked_B1S = torch.full(
            (B, 1, config.tokens_per_frame), config.mask_token_id, dtype=torch.long, device=self.tokens.device
        )
        control = self._paired(control)
        return self._logits_of_new_frame(masked_B1S, control, self._next_state(control)).float()

    def _decode(self, control: Control, state, temperature: float, generator) -> torch.Tensor:
        """The new frame's tokens (B, 1, S) by MaskGIT decoding under `control` and `state` (paired when guided). A
        step keeps the most confident of the positions still masked, each with all its codes (a position's
        confidence: its codes' log-probabilities summed)."""
        model, config = self.model, self.model.config
        B, S, N = self.done.shape[0], config.tokens_per_frame, config.positions_per_frame
        frame_B1S = torch.full((B, 1, S), config.mask_token_id, dtype=torch.long, device=self.tokens.device)
        known_BN = torch.zeros(B, N, dtype=torch.bool, device=frame_B1S.device)
        steps = config.maskgit_steps
        for step in range(1, steps + 1):
            logits_BSV = self._logits_of_new_frame(frame_B1S, control, state).float()
            if temperature > 0:
                uniform = torch.rand(logits_BSV.shape, generator=generator, device=logits_BSV.device)
                sample_BS = (logits_BSV / temperature - torch.log(-torch.log(uniform))).argmax(-1)
            else:
                sample_BS = logits_BSV.argmax(-1)
            known_BS = model.ungroup(known_BN[:, None, :, None].expand(-1, -1, -1, config.codes_per_position))[:, 0]
            if step == steps:  # the last step keeps every token still masked
                frame_B1S[:, 0] = torch.where(known_BS, frame_B1S[:, 0], sample_BS)
                break
            # MaskGIT's confidence order; annealed noise and 1X GENIE's random order measured within noise of it
            # (docs/results/world_model/control_levers.md) and were removed
            rank_BS = logits_BSV.log_softmax(-1).gather(-1, sample_BS[..., None]).squeeze(-1)
            rank_BN = model.group(rank_BS[:, None])[:, 0].sum(-1)
            n_known = max(int(N * (1 - math.cos(math.pi / 2 * step / steps))), 1)
            keep_BN = known_BN.scatter(1, rank_BN.masked_fill(known_BN, math.inf).topk(n_known).indices, True)
            keep_BS = model.ungroup(keep_BN[:, None, :, None].expand(-1, -1, -1, config.codes_per_position))[:, 0]
            frame_B1S[:, 0] = torch.where(keep_BS & ~known_BS, sample_BS, frame_B1S[:, 0])
            known_BN = keep_BN
        return frame_B1S

    def _replay(self, control: Control, temperature: float, generator) -> tuple[torch.Tensor, ...]:
        """The frame's tokens, done and features from the CUDA graph of this cache, control and temperature
        (captured at the first frame that asks for it)."""
        key = (temperature, id(generator), *(None if t is None else tuple(t.shape) for t in control))
        graph = self.cache.graphs.get(key)
        if graph is None:
            graph = self.cache.graphs[key] = CapturedFrame(self, control, temperature, generator)
        outputs = graph(self, control)
        self.cache.frames += 1  # the graph moved the device-side state; this is the host's count
        return outputs

    def _frame_on_device(self, control: Control, temperature: float, generator) -> tuple[torch.Tensor, ...]:
        """One frame's whole work on the device, the cache moved to the next slot: what a CUDA graph records."""
        outputs = self._frame(control, temperature, generator)
        self.cache.advance()
        return outputs

    @torch.no_grad()
    def observe(self, frame_B1S, control: Control, state: torch.Tensor | None = None) -> torch.Tensor:
        """Append a known frame (generated, or real for teacher forcing) to the rollout, with its state (B, D) where
        known (else, with a state channel, the predicted one); returns its done (B,)."""
        control = self._paired(control)
        if state is None:
            state = self._next_state(control)
        elif self.states is not None:
            state = torch.cat([state, state])[:, None] if self.guided else state[:, None]
        done, features = self._read(frame_B1S, control, state)
        if self.cache is not None:
            self.cache.commit()
        self._remember(frame_B1S, control, done, features, state)
        return done

    def _read(self, frame_B1S, control: Control, state) -> tuple[torch.Tensor, torch.Tensor]:
        """Done (B,) and features (B, C) of a frame after the rollout's; with the cache, its keys and values are
        written into the frame's slot."""
        model, B = self.model, frame_B1S.shape[0]
        if self.guided:
            frame_B1S = torch.cat([frame_B1S, frame_B1S])
        if self.cache is not None:
            hidden_BTNC, _ = model.compute_hidden(frame_B1S, control, self.cache, states=state, anchor=self.anchor)
        else:
            tokens = torch.cat([self.tokens, frame_B1S], 1)
            controls, states = self._concat_controls(self.control, control), self._concat_states(state)
            hidden_BTNC, _ = model.compute_hidden(tokens, controls, states=states, anchor=self.anchor)
        return readout(model, hidden_BTNC, B)

    def _remember(self, frame_B1S, control: Control, done: torch.Tensor, features: torch.Tensor, state) -> None:
        """Keep the new frame, its control, state, done and features, and slide the window."""
        self.done, self.features = done, features
        if self.guided:
            frame_B1S = torch.cat([frame_B1S, frame_B1S])
        self.tokens = torch.cat([self.tokens, frame_B1S], 1)
        self.control = self._concat_controls(self.control, control)
        self.states = self._concat_states(state)
        self.frames_seen += 1
        self.slide()

    def slide(self) -> None:
        """Keep the last window - 1 frames: with the new one, a generated frame sees `window` frames."""
        keep = self.model.config.window - 1
        self.tokens = self.tokens[:, -keep:]
        self.control = self.control.frames(slice(-keep, None))
        if self.states is not None:
            self.states = self.states[:, -keep:]

    def _concat_states(self, state) -> torch.Tensor | None:
        return None if self.states is None else torch.cat([self.states, state], 1)

    def _paired(self, control: Control) -> Control:
        """A frame's control, followed by the null control when guided."""
        return Control.cat([control, self.model.null_control(control)], 0) if self.guided else control

    def _logits_of_new_frame(self, frame_B1S, control: Control, state) -> torch.Tensor:
        """Logits (B, S, V) of the frame being generated (guided: null + scale * (control - null))."""
        if self.guided:
            frame_B1S = torch.cat([frame_B1S, frame_B1S])
        if self.cache is not None:
            logits = self.model.compute_logits(frame_B1S, control, self.cache, states=state, anchor=self.anchor)[0]
            logits = logits[:, -1]
        else:  # without the cache: recompute the whole window (past frames + the new one), as the paper's code did
            tokens = torch.cat([self.tokens, frame_B1S], 1)
            controls, states = self._concat_controls(self.control, control), self._concat_states(state)
            logits = self.model.compute_logits(tokens, controls, states=states, anchor=self.anchor)[0][:, -1]
        if not self.guided:
            return logits
        conditioned, null = logits.float().chunk(2)
        return null + self.model.config.guidance_scale * (conditioned - null)

    def _concat_controls(self, past: Control, new: Control) -> Control:
        if self.model.config.control == "text":
            return past  # one instruction for every frame
        return Control.cat([past, new], 1)


class CapturedFrame:
    """One frame of a cached rollout on CUDA, recorded as a CUDA graph: the control and the rollout's latest
    features and state are copied into the graph's inputs, the graph replayed, its outputs (tokens (B, 1, S), done
    (B,), features (B, C), state (B, 1, D) or None) copied out. The cache's rings and device-side state are the
    graph's memory, so the graph serves every frame of every episode that refills the same cache (its anchor frame
    copied in as well)."""

    def __init__(self, rollout: Rollout, control: Control, temperature: float, generator):
        cache = rollout.cache
        # Warm up on a side stream (cuBLAS handles, allocator pools), then put back the state a pass moves: the
        # cache's position (its slot's keys and values are written again by every pass) and the generator.
        position = cache.position.clone()
        rng = generator.get_state() if generator is not None else torch.cuda.get_rng_state(cache.position.device)
        side = torch.cuda.Stream()
        side.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(side), self._autocast():
            for _ in range(WARMUP_FRAMES):
                rollout._frame_on_device(control, temperature, generator)
                cache.position.copy_(position - 1)
                cache.advance()
        torch.cuda.current_stream().wait_stream(side)
        if generator is not None:
            generator.set_state(rng)
        else:
            torch.cuda.set_rng_state(rng, cache.position.device)
        self.control = Control(*(None if t is None else t.clone() for t in control))
        self.features = rollout.features.clone()
        self.state = None if rollout.states is None else rollout.states[:, -1:].clone()  # all a cached frame reads
        self.anchor = None if rollout.anchor is None else rollout.anchor.clone()  # a new episode's is copied in
        live = rollout.features, rollout.states, rollout.anchor
        rollout.features, rollout.states, rollout.anchor = self.features, self.state, self.anchor
        self.graph = torch.cuda.CUDAGraph()
        if generator is not None:
            self.graph.register_generator_state(generator)
        with self._autocast(), torch.cuda.graph(self.graph):
            self.outputs = rollout._frame_on_device(self.control, temperature, generator)
        rollout.features, rollout.states, rollout.anchor = live

    @staticmethod
    def _autocast():
        """The caller's autocast, without its cache of cast weights (a graph must own every tensor it reads)."""
        return torch.autocast(
            "cuda",
            dtype=torch.get_autocast_dtype("cuda"),
            enabled=torch.is_autocast_enabled("cuda"),
            cache_enabled=False,
        )

    def __call__(self, rollout: Rollout, control: Control) -> tuple[torch.Tensor | None, ...]:
        for static, given in zip(self.control, control, strict=True):
            if static is not None:
                static.copy_(given)
        self.features.copy_(rollout.features)
        if self.state is not None:
            self.state.copy_(rollout.states[:, -1:])
        if self.anchor is not None:
            self.anchor.copy_(rollout.anchor)
        self.graph.replay()
        return tuple(None if t is None else t.clone() for t in self.outputs)
