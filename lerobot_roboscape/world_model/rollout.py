"""A running generation of a world model: start from prompt frames, predict the next frame by MaskGIT decoding,
observe known frames, slide the window.

With the key/value cache (the default) a new frame is computed against the cached keys and values of the frames
before it. Without it, every step re-reads the whole window of past frames, as the paper's code (1xgpt's
`STMaskGIT.generate`) does. Both give the same tokens while the rollout fits in the window; past it, a cached frame
keeps the keys and values it was computed with (its own window of context), where recomputing re-reads the oldest
frames of the window without theirs.

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


@dataclass
class Rollout:
    """What a running generation remembers: the last `window - 1` frames as tokens, their controls, and (with the
    cache) every layer's keys and values of those frames. When guided, tokens, controls and cache hold the samples
    under their control followed by the same samples under the null control."""

    model: nn.Module  # an STWorldModel (not imported: it imports this module to generate)
    tokens: torch.Tensor  # (B, T, S) long, (2B, T, S) when guided
    control: Control  # (B, T, L, C) for the action model; (B, 1, L, C) shared for the text model
    cache: KVCache | None  # None when generating by recomputing the window
    done: torch.Tensor  # (B,) done probability of the latest frame
    features: torch.Tensor  # (B, C) the latest frame's final hidden state, averaged over its tokens
    frames_seen: int = 0
    guided: bool = False
    capture: bool = False

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
    ) -> "Rollout":
        """Read the prompt frames (real tokens) with their controls. `guided`: apply the model's guidance scale
        (reading known frames only, as teacher forcing does, needs no guidance). `capture`: replay each frame's
        work as a CUDA graph (a cached rollout on CUDA). `reuse`: an earlier rollout of the same model whose cache
        (and the graphs captured against it) this one refills when the shapes match."""
        if capture and (not use_cache or prompt_BPS.device.type != "cuda"):
            raise ValueError(
                f"capture needs the key/value cache on a CUDA device (use_cache={use_cache}, "
                f"device {prompt_BPS.device})"
            )
        guided = guided and model.config.guidance_scale != 1
        B = prompt_BPS.shape[0]
        if guided:
            prompt_BPS = torch.cat([prompt_BPS, prompt_BPS])
            control = Control.cat([control, model.null_control(control)], 0)
        cache = None
        if use_cache:
            reusable = reuse is not None and reuse.cache is not None and reuse.model is model
            cache = reuse.cache if reusable else KVCache(model.config.n_layer, model.config.window)
        hidden_BTSC, _ = model.compute_hidden(prompt_BPS, control, fill=cache)
        done = torch.sigmoid(model.done_logits(hidden_BTSC[:B, -1:])[:, 0].float())
        features = hidden_BTSC[:B, -1].mean(dim=1)
        rollout = cls(model, prompt_BPS, control, cache, done, features, prompt_BPS.shape[1], guided, capture)
        rollout.slide()
        return rollout

    @torch.no_grad()
    def predict_next_frame(
        self, control: Control, temperature: float = 0.0, generator: torch.Generator | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Generate the next frame under `control` ((B, 1, L, C)) in `maskgit_steps` parallel decoding steps, each
        keeping the most confident of the tokens still masked, then observe it. Returns
        tokens (B, S) and done (B,)."""
        control = self._paired(control)
        if self.capture:
            frame_B1S, done, features = self._replay(control, temperature, generator)
        else:
            frame_B1S = self._decode(control, temperature, generator)
            done, features = self._read(frame_B1S, control)
            if self.cache is not None:
                self.cache.commit()
        self._remember(frame_B1S, control, done, features)
        return frame_B1S[:, 0], done

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
        return self._logits_of_new_frame(masked_B1S, self._paired(control)).float()

    def _decode(self, control: Control, temperature: float, generator) -> torch.Tensor:
        """The new frame's tokens (B, 1, S) by MaskGIT decoding under `control` (paired when guided)."""
        config = self.model.config
        B, S = self.done.shape[0], config.tokens_per_frame
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
            # MaskGIT's confidence order; annealed noise and 1X GENIE's random order measured within noise of it
            # (docs/results/world_model/control_levers.md) and were removed
            rank_BS = logits_BSV.log_softmax(-1).gather(-1, sample_BS[..., None]).squeeze(-1)
            n_known = max(int(S * (1 - math.cos(math.pi / 2 * step / steps))), 1)
            keep_BS = known_BS.scatter(1, rank_BS.masked_fill(known_BS, math.inf).topk(n_known).indices, True)
            frame_B1S[:, 0] = torch.where(keep_BS & ~known_BS, sample_BS, frame_B1S[:, 0])
            known_BS = keep_BS
        return frame_B1S

    def _replay(self, control: Control, temperature: float, generator) -> tuple[torch.Tensor, ...]:
        """The frame's tokens, done and features from the CUDA graph of this cache, control and temperature
        (captured at the first frame that asks for it)."""
        key = (temperature, id(generator), *(None if t is None else tuple(t.shape) for t in control))
        graph = self.cache.graphs.get(key)
        if graph is None:
            graph = self.cache.graphs[key] = CapturedFrame(self, control, temperature, generator)
        outputs = graph(control)
        self.cache.frames += 1  # the graph moved the device-side state; this is the host's count
        return outputs

    def _frame_on_device(self, control: Control, temperature: float, generator) -> tuple[torch.Tensor, ...]:
        """One frame's whole work on the device, the cache moved to the next slot: what a CUDA graph records."""
        frame_B1S = self._decode(control, temperature, generator)
        done, features = self._read(frame_B1S, control)
        self.cache.advance()
        return frame_B1S, done, features

    @torch.no_grad()
    def observe(self, frame_B1S, control: Control) -> torch.Tensor:
        """Append a known frame (generated, or real for teacher forcing) to the rollout; returns its done (B,)."""
        control = self._paired(control)
        done, features = self._read(frame_B1S, control)
        if self.cache is not None:
            self.cache.commit()
        self._remember(frame_B1S, control, done, features)
        return done

    def _read(self, frame_B1S, control: Control) -> tuple[torch.Tensor, torch.Tensor]:
        """Done (B,) and features (B, C) of a frame after the rollout's; with the cache, its keys and values are
        written into the frame's slot."""
        model, B = self.model, frame_B1S.shape[0]
        if self.guided:
            frame_B1S = torch.cat([frame_B1S, frame_B1S])
        if self.cache is not None:
            hidden_BTSC, _ = model.compute_hidden(frame_B1S, control, self.cache)
        else:
            tokens = torch.cat([self.tokens, frame_B1S], 1)
            hidden_BTSC, _ = model.compute_hidden(tokens, self._concat_controls(self.control, control))
        done = torch.sigmoid(model.done_logits(hidden_BTSC[:B, -1:])[:, 0].float())
        return done, hidden_BTSC[:B, -1].mean(dim=1)

    def _remember(self, frame_B1S, control: Control, done: torch.Tensor, features: torch.Tensor) -> None:
        """Keep the new frame, its control, done and features, and slide the window."""
        self.done, self.features = done, features
        if self.guided:
            frame_B1S = torch.cat([frame_B1S, frame_B1S])
        self.tokens = torch.cat([self.tokens, frame_B1S], 1)
        self.control = self._concat_controls(self.control, control)
        self.frames_seen += 1
        self.slide()

    def slide(self) -> None:
        """Keep the last window - 1 frames: with the new one, a generated frame sees `window` frames."""
        keep = self.model.config.window - 1
        self.tokens = self.tokens[:, -keep:]
        self.control = self.control.frames(slice(-keep, None))

    def _paired(self, control: Control) -> Control:
        """A frame's control, followed by the null control when guided."""
        return Control.cat([control, self.model.null_control(control)], 0) if self.guided else control

    def _logits_of_new_frame(self, frame_B1S, control: Control) -> torch.Tensor:
        """Logits (B, S, V) of the frame being generated (guided: null + scale * (control - null))."""
        if self.guided:
            frame_B1S = torch.cat([frame_B1S, frame_B1S])
        if self.cache is not None:
            logits = self.model.compute_logits(frame_B1S, control, self.cache)[0][:, -1]
        else:  # without the cache: recompute the whole window (past frames + the new one), as the paper's code did
            tokens = torch.cat([self.tokens, frame_B1S], 1)
            logits = self.model.compute_logits(tokens, self._concat_controls(self.control, control))[0][:, -1]
        if not self.guided:
            return logits
        conditioned, null = logits.float().chunk(2)
        return null + self.model.config.guidance_scale * (conditioned - null)

    def _concat_controls(self, past: Control, new: Control) -> Control:
        if self.model.config.control == "text":
            return past  # one instruction for every frame
        return Control.cat([past, new], 1)


class CapturedFrame:
    """One frame of a cached rollout on CUDA, recorded as a CUDA graph: the control is copied into the graph's
    input, the graph replayed, its outputs (tokens (B, 1, S), done (B,), features (B, C)) copied out. The cache's
    rings and device-side state are the graph's memory, so the graph serves every frame of every episode that
    refills the same cache."""

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
        self.graph = torch.cuda.CUDAGraph()
        if generator is not None:
            self.graph.register_generator_state(generator)
        with self._autocast(), torch.cuda.graph(self.graph):
            self.outputs = rollout._frame_on_device(self.control, temperature, generator)

    @staticmethod
    def _autocast():
        """The caller's autocast, without its cache of cast weights (a graph must own every tensor it reads)."""
        return torch.autocast(
            "cuda",
            dtype=torch.get_autocast_dtype("cuda"),
            enabled=torch.is_autocast_enabled("cuda"),
            cache_enabled=False,
        )

    def __call__(self, control: Control) -> tuple[torch.Tensor, ...]:
        for static, given in zip(self.control, control, strict=True):
            if static is not None:
                static.copy_(given)
        self.graph.replay()
        return tuple(t.clone() for t in self.outputs)
