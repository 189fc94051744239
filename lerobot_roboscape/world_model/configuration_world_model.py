from dataclasses import dataclass

import draccus

from roboscape_core.errors import InvalidInputError

CONTROLS = ("action", "text")
DONE_LOSSES = ("balanced_bce", "rmse")
ADALN_GATES = ("none", "one_plus")


@dataclass
class WorldModelConfig(draccus.ChoiceRegistry):
    """A Genie-style spatial-temporal transformer predicting the next frame's tokens and a done signal.

    A frame is the token grids of all camera views side by side: n_cameras * tokens_per_side ** 2 tokens, each view
    tokenized on its own (the paper's code stacked the two views into one image; separate grids keep the tokenizer
    camera-agnostic and the views' borders clean). Choose a preset with `--wm.type=tiny|paper`, then override.

    Args:
        control: "action" (7-D actions through an MLP encoder) or "text" (the instruction through a T5 encoder).
        n_cameras: camera views per frame.
        tokens_per_side: side of one view's token grid (the tokenizer's).
        vocab_size: tokenizer codebook size.
        action_dim: width of the actions (action model).
        frame_skip: control steps per model frame (k): a frame's control is the k actions that lead to it, and
            the model steps once per executed action chunk (DIAMOND, IRIS and Cosmos step every 4 frames). Lengths
            a user gives (episode length, horizon, goal search) stay in control steps. 1: a frame per action.
        action_mean, action_std: per-dimension statistics of the training data's actions (LeRobot's
            dataset.meta.stats["action"]), filled in by training: the action model reads (action - mean) / std,
            with std floored at ACTION_STD_FLOOR. Saved with the model; a saved action model without them is
            refused at load.
        state: the robot's state (`observation.state`: joint positions and the TCP pose) as a channel of every frame:
            its embedding is added to each position of the frame, and a head predicts the next frame's state from
            this frame's state, its hidden state and the next frame's control; a rollout starts from the prompt's
            real states and feeds back its own predictions, each frame's tokens generated under its predicted
            state. The arm is the one part of the scene the data records exactly (DINO-WM, the 1X challenge's
            winner); without it a rollout that loses the arm in one frame has nothing to find it again by.
        state_dim: width of the states.
        state_mean, state_std: per-dimension statistics of the training data's states, filled in by training, as the
            actions' (std floored at STATE_STD_FLOOR). A saved model with a state channel and without them is
            refused at load.
        state_min, state_max: per-dimension range of the training data's states, filled in by training: where a
            rollout's predicted state has left it, the model has seen nothing of what follows (`roboscape_wm`'s
            state_margin halts the episode there).
        text_encoder: T5 checkpoint (Hub id or local directory) for the text model; None builds a small random
            T5 with a byte-level tokenizer (tests and the tiny preset: instructions are told apart, not understood).
        text_max_length: instructions are truncated to this many T5 tokens.
        patch: a transformer position holds patch x patch codes of one view's grid: one embedding of its codes (the
            sum of one per place in the patch), an output head per code, masked and decoded per position. 2 on a
            16x16 grid: 128 positions per two-view frame instead of 512, so that attention and the MLPs cost a
            quarter per frame on the 2 CPU cores.
        n_layer: spatial-temporal blocks.
        n_head: attention heads.
        d_model: width of the transformer.
        mlp_ratio: MLP hidden width as a multiple of d_model.
        dropout: dropout in attention and MLPs.
        window: frames the model sees at once (training clip length and generation context).
        prompt_frames: real frames given before prediction starts in evaluation.
        anchor: every frame's cross-attention also reads the episode's first frame (its real tokens, with a learned
            anchor embedding), which the rollout keeps for the whole episode: what has not moved can be copied from
            the real start instead of from the model's own generated past, which falls out of the window after
            `window` frames and drifts (issue 72: 100-step rollouts drifted into texture).
        maskgit_steps: parallel decoding steps per generated frame.
        adaln: the frame's control in every block's LayerNorms (scale, shift and gate from the pooled control, the
            projection zero-initialised as in DiT, each sub-layer gated by 1 + g so training starts from the block
            without it): "one_plus" or "none". Measured on the synthetic motion world
            (docs/results/world_model/control_levers.md): 0.25 -> 0.94 at 10 minutes alone, and the combination
            without it 0.57 against 0.98; DiT's AdaLN-Zero gate (g alone) reached 0.47 and was removed.
        normalize_control: LayerNorm the control tokens before each block's cross-attention and the pooled control
            before the adaptive LayerNorm (raw, they start ~8x smaller than the image tokens). Measured there: the
            combination without it 0.81 against 0.98.
        control_dropout: share of training frames (action model) or clips (text model) whose control is replaced
            by the learned null control, so that the model also learns an unconditional mode for guidance.
        guidance_scale: classifier-free guidance at generation, logits = null + scale * (control - null); 1 is
            off. Needs a model trained with control_dropout > 0. Measured on the synthetic motion world: on a model
            that half-follows its actions, guidance 2-4 lifts retrieval from 0.57 to 0.82 / 0.89; on the robot's
            data it did not (docs/results/world_model/report.md), so the presets leave both off.
        corrupt_max: training replaces a share of the codes left unmasked (the context every prediction reads) with
            random codes, the share drawn per clip uniformly in [0, corrupt_max] (1xgpt's collator after Copilot-4D,
            GameNGen's context noise), so that the model learns to read through the mistakes of its own rollouts.
        corrupt_held: the corrupted codes are the same, replaced by the same random codes, in every frame of a
            clip, as a rollout's mistakes persist from frame to frame: no frame of the window shows what they hide,
            only an anchor does (`anchor`), so that the model learns to repair its rollouts from it.
        clean_frame_prob: chance that a training frame stays unmasked, so the model also learns from clean
            context as it sees at generation time.
        changed_weight: weight of the masked tokens that differ from the previous frame's token at the same place,
            against 1 for the rest. On the robot's data a third of the tokens change per model frame (the arm and
            what it moves), and copying the previous frame already scores two thirds of the tokens without reading
            the action: weighting the changed ones makes the dynamics, and so the action, carry the loss. Measured
            on the robot's data (docs/results/world_model/report.md): 5x is the bench preset's.
        masked_head: the output head reads the masked positions only (True), or every position with the loss
            weighing the masked codes (False), which keeps a training step from waiting on the device (boolean
            indexing would); null: True on the CPU, False elsewhere. The head's vocab_size outputs per code are
            most of a step's FLOPs at d_model 128, and about half the positions are masked: on the 2 CPU cores it
            gives the bench preset 1.5-1.6x the clips/s (scripts/benchmarks/benchmark_wm_training.py). The loss is
            the same either way.
        done_hidden: hidden width of the done head.
        done_weight: weight of the done loss.
        done_loss: "balanced_bce" (binary cross-entropy averaged over done frames and over the others separately,
            so that the rare done frames weigh as much as the rest) or "rmse" (the paper's RMSE of the done
            probability, which a head predicting "never done" nearly minimises when done frames are few).
    """

    # Control.
    control: str = "action"
    action_dim: int = 7
    frame_skip: int = 4
    action_mean: list[float] | None = None
    action_std: list[float] | None = None
    state: bool = True
    state_dim: int = 16
    state_mean: list[float] | None = None
    state_std: list[float] | None = None
    state_min: list[float] | None = None
    state_max: list[float] | None = None
    text_encoder: str | None = None
    text_max_length: int = 64
    # Frames.
    n_cameras: int = 2
    tokens_per_side: int = 8
    vocab_size: int = 256
    patch: int = 1
    # Transformer.
    n_layer: int = 2
    n_head: int = 4
    d_model: int = 128
    mlp_ratio: int = 4
    dropout: float = 0.0
    # Generation.
    window: int = 8
    prompt_frames: int = 2
    anchor: bool = False
    maskgit_steps: int = 2
    guidance_scale: float = 1.0
    # Control path.
    adaln: str = "one_plus"
    normalize_control: bool = True
    control_dropout: float = 0.0
    # Training.
    clean_frame_prob: float = 0.25
    corrupt_max: float = 0.0
    corrupt_held: bool = False
    changed_weight: float = 1.0
    masked_head: bool | None = None
    done_hidden: int = 128
    done_weight: float = 1.0
    done_loss: str = "balanced_bce"

    def __post_init__(self):
        if self.control not in CONTROLS:
            raise InvalidInputError(f"control must be one of {CONTROLS}, got {self.control!r}")
        if self.d_model % self.n_head or (self.d_model // self.n_head) % 2:
            raise InvalidInputError(f"d_model={self.d_model} must split into n_head={self.n_head} heads of even width")
        if not 1 <= self.prompt_frames < self.window:
            raise InvalidInputError(f"prompt_frames={self.prompt_frames} must be in [1, window={self.window})")
        if self.done_loss not in DONE_LOSSES:
            raise InvalidInputError(f"done_loss must be one of {DONE_LOSSES}, got {self.done_loss!r}")
        if self.maskgit_steps < 1:
            raise InvalidInputError(f"maskgit_steps must be >= 1, got {self.maskgit_steps}")
        if self.frame_skip < 1:
            raise InvalidInputError(f"frame_skip must be >= 1, got {self.frame_skip}")
        for name in ("action_mean", "action_std"):
            if (stats := getattr(self, name)) is not None and len(stats) != self.action_dim:
                raise InvalidInputError(
                    f"{name} has {len(stats)} dimensions but the actions have action_dim={self.action_dim}: "
                    "statistics of another action layout; retrain the world model on this dataset (roboscape-train-wm)"
                )
        for name in ("state_mean", "state_std", "state_min", "state_max"):
            if (stats := getattr(self, name)) is not None and len(stats) != self.state_dim:
                raise InvalidInputError(
                    f"{name} has {len(stats)} dimensions but the states have state_dim={self.state_dim}: statistics "
                    "of another state layout; retrain the world model on this dataset (roboscape-train-wm)"
                )
        for first, second in (("action_mean", "action_std"), ("state_mean", "state_std"), ("state_min", "state_max")):
            if (getattr(self, first) is None) != (getattr(self, second) is None):
                raise InvalidInputError(f"{first} and {second} are set together (from dataset.meta.stats)")
        if self.patch < 1 or self.tokens_per_side % self.patch:
            raise InvalidInputError(
                f"patch={self.patch} must divide tokens_per_side={self.tokens_per_side} (a position is patch x patch "
                "codes of one view)"
            )
        if not 0 <= self.corrupt_max < 1:
            raise InvalidInputError(f"corrupt_max must be in [0, 1), got {self.corrupt_max}")
        if self.adaln not in ADALN_GATES:
            raise InvalidInputError(f"adaln must be one of {ADALN_GATES}, got {self.adaln!r}")
        for name in ("control_dropout", "clean_frame_prob"):
            if not 0 <= getattr(self, name) < 1:
                raise InvalidInputError(f"{name} must be in [0, 1), got {getattr(self, name)}")
        if self.changed_weight <= 0:
            raise InvalidInputError(f"changed_weight must be > 0, got {self.changed_weight}")
        if self.guidance_scale != 1 and self.control_dropout == 0:
            raise InvalidInputError(
                f"guidance_scale={self.guidance_scale} needs a null control: train with control_dropout > 0"
            )

    @classmethod
    def default_choice_name(cls) -> str:
        return "tiny"  # `--wm.d_model=64` alone then edits the tiny preset

    @property
    def tokens_per_frame(self) -> int:
        return self.n_cameras * self.tokens_per_side**2

    @property
    def codes_per_position(self) -> int:
        return self.patch**2

    @property
    def positions_per_frame(self) -> int:
        """Transformer positions per frame: each view's grid in patch x patch blocks."""
        return self.n_cameras * (self.tokens_per_side // self.patch) ** 2

    @property
    def mask_token_id(self) -> int:
        return self.vocab_size


@WorldModelConfig.register_subclass("tiny")
@dataclass
class TinyWorldModelConfig(WorldModelConfig):
    """2 layers, d_model 128, window 8: trains on 2 CPU cores in minutes."""


@WorldModelConfig.register_subclass("bench")
@dataclass
class BenchWorldModelConfig(WorldModelConfig):
    """The tiny model's width on the bench tokenizer's 16x16 grids, with a window of 6, a position 2x2 codes (128
    positions per two-view frame): 3.9x the clips of a code per position on 2 CPU cores, and at equal CPU minutes a
    better arm and more motion in its rollouts (docs/results/world_model/levers70). On the bench data, 7,500 steps at
    batch 4 (10 clips/s on 2 cores) take 48 minutes; two seeds' rollouts then follow the robot's state and pick their
    own future by pixels in 0.55-0.6 of starts (docs/results/world_model/bench70). d_model 192 trailed it at equal
    minutes in two seeds (docs/results/world_model/wide70): on 2 cores the clips are worth more than the width.
    Corrupted context (up to 0.2) cut the TCP's drift over 48 control steps from 41% to 30-31% of the distance moved
    IND and from 61% to 42-45% OOD in both seeds, at the same clips/s (docs/results/world_model/corrupt70).
    Changed tokens weigh 5x: on the robot's data copying the previous frame already scores two thirds of the tokens."""

    tokens_per_side: int = 16
    vocab_size: int = 1024
    patch: int = 2
    window: int = 6
    changed_weight: float = 5.0
    corrupt_max: float = 0.2


@WorldModelConfig.register_subclass("gpu")
@dataclass
class GpuWorldModelConfig(BenchWorldModelConfig):
    """The bench's frames (two 16x16 views, 1024 codes) at the size one GPU trains in minutes: 6 layers of width 384
    (30M parameters, 20x the bench preset's) and a window of 8 frames; a training step costs 0.46 TFLOP per clip. Its
    weights in bf16 (57 MiB) fit what one call of a lent GPU machine brings back (64 MiB)."""

    patch: int = 1  # as measured on the GPU; 2x2 codes and corruption were judged on the CPU only
    corrupt_max: float = 0.0
    n_layer: int = 6
    n_head: int = 6
    d_model: int = 384
    window: int = 8
    done_hidden: int = 256


@WorldModelConfig.register_subclass("paper")
@dataclass
class PaperWorldModelConfig(WorldModelConfig):
    """The paper's model: 32 layers, 8 heads, d_model 512, 16x16 tokens per view, window 16 with 8 prompt frames,
    2 MaskGIT steps per frame. Use with the paper tokenizer preset (4096 codes) and a T5 checkpoint."""

    tokens_per_side: int = 16
    vocab_size: int = 4096
    n_layer: int = 32
    n_head: int = 8
    d_model: int = 512
    dropout: float = 0.1
    window: int = 16
    prompt_frames: int = 8
    done_hidden: int = 512
    text_encoder: str | None = "google-t5/t5-base"
