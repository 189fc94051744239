"""Synthetic token worlds where nothing but the control predicts the change: the world model's control path, tested.

A frame is one G x G token grid: a per-start random background texture and a 2 x 2 square (its own token) on it.
Only the square moves, and only the control says where:
- *wiring*: the action alone says where the square is next (its first two dimensions name the cell);
- *motion*: the action moves the square one cell from where it is (the sign of its first two dimensions), clamped
  at the borders;
- *text*: the instruction says which way the square moves, one cell per step.
Actions are 7-D and small, as the robot planner's are (at most ACTION_SCALE of the range, rotation almost still).
The square's cell is the world's state (the robot's `observation.state` in the real data), 2-D.

`retrieval` asks the world model to roll out from one start under K controls and scores how often each rollout is
nearer its own real future than the others' (token agreement, averaged over the horizon): chance is 1 / K.
"""

import time
from dataclasses import dataclass

import numpy as np
import torch

from lerobot_roboscape.world_model.configuration_world_model import TinyWorldModelConfig
from lerobot_roboscape.world_model.measures.retrieval import retrieval_accuracy
from lerobot_roboscape.world_model.modeling_world_model import STWorldModel

WORLDS = ("wiring", "motion", "text")
ACTION_SCALE = 0.35  # the planner uses at most this share of the translation range
ACTION_DIM = 7
STATE_DIM = 2  # the square's cell (x, y)
SQUARE = 2
INSTRUCTIONS = {"move the square right": (1, 0), "move the square down": (0, 1)}


@dataclass
class SyntheticWorld:
    """Args:
    kind: "wiring", "motion" or "text".
    grid: side of the token grid.
    vocab_size: token codebook size; the last token is the square, the others the background texture.
    background_tokens: distinct background tokens (0..background_tokens - 1); 1 = a plain background.
    """

    kind: str = "motion"
    grid: int = 8
    vocab_size: int = 16
    background_tokens: int = 4

    def __post_init__(self):
        if self.kind not in WORLDS:
            raise ValueError(f"kind must be one of {WORLDS}, got {self.kind!r}")
        if not 1 <= self.background_tokens < self.vocab_size:
            raise ValueError(f"background_tokens={self.background_tokens} must be in [1, vocab_size)")

    @property
    def square_token(self) -> int:
        return self.vocab_size - 1

    @property
    def cells(self) -> int:
        """Positions of the square's top-left corner per axis."""
        return self.grid - SQUARE + 1

    # ---- dynamics ------------------------------------------------------------------------------------------

    def random_controls(self, rng: np.random.Generator, n: int, steps: int) -> np.ndarray:
        """Actions (n, steps, 7) for wiring and motion; instruction indices (n,) for text."""
        if self.kind == "text":
            return rng.integers(0, len(INSTRUCTIONS), n)
        actions = rng.uniform(-0.02, 0.02, (n, steps, ACTION_DIM)) * ACTION_SCALE  # rotation and gripper: still
        if self.kind == "wiring":
            actions[..., :2] = rng.uniform(-ACTION_SCALE, ACTION_SCALE, (n, steps, 2))
        else:  # one of the 8 directions or stay, with a little noise
            actions[..., :2] = rng.integers(-1, 2, (n, steps, 2)) * ACTION_SCALE * rng.uniform(0.7, 1, (n, steps, 1))
        return actions.astype(np.float32)

    def random_starts(self, rng: np.random.Generator, n: int, steps: int) -> tuple[np.ndarray, np.ndarray]:
        """Backgrounds (n, G, G) and square positions (n, 2). Text starts leave room for `steps` cells each way, so
        that the two instructions lead apart."""
        background = rng.integers(0, self.background_tokens, (n, self.grid, self.grid))
        high = max(self.cells - steps, 1) if self.kind == "text" else self.cells
        return background, rng.integers(0, high, (n, 2))

    def next_position(self, position: np.ndarray, control: np.ndarray) -> np.ndarray:
        """position (n, 2) after one step of control (actions (n, 7) or instruction indices (n,))."""
        if self.kind == "wiring":
            cell = np.floor((control[:, :2] / ACTION_SCALE + 1) / 2 * self.cells)
            return np.clip(cell, 0, self.cells - 1).astype(np.int64)
        if self.kind == "motion":
            step = np.sign(np.round(control[:, :2] / ACTION_SCALE))
        else:
            step = np.array(list(INSTRUCTIONS.values()))[control]
        return np.clip(position + step, 0, self.cells - 1).astype(np.int64)

    def render(self, background: np.ndarray, position: np.ndarray) -> np.ndarray:
        """Tokens (n, G * G): the background with the square drawn at `position`."""
        frame = background.copy()
        for i, (x, y) in enumerate(position):
            frame[i, y : y + SQUARE, x : x + SQUARE] = self.square_token
        return frame.reshape(len(frame), -1)

    def episodes(self, rng: np.random.Generator, n: int, steps: int, controls=None, starts=None) -> dict:
        """n episodes of `steps` controls: tokens (n, steps + 1, S), states (n, steps + 1, 2) and the controls."""
        background, position = self.random_starts(rng, n, steps) if starts is None else starts
        controls = self.random_controls(rng, n, steps) if controls is None else controls
        frames, positions = [self.render(background, position)], [position]
        for t in range(steps):
            position = self.next_position(position, controls if self.kind == "text" else controls[:, t])
            frames.append(self.render(background, position))
            positions.append(position)
        return {
            "tokens": np.stack(frames, 1),
            "states": np.stack(positions, 1).astype(np.float32),
            "controls": controls,
        }

    # ---- what the world model reads ------------------------------------------------------------------------

    def training_batch(
        self, step: int, batch_size: int, window: int, seed: int = 0, shuffle: bool = False, frame_skip: int = 1
    ) -> dict:
        """A batch in the world-model training layout (ClipSampler's), a pure function of (seed, step): tokens
        (B, T, S) every `frame_skip` (k) control steps, anchor (B, S) the episode's first frame, actions
        (B, T, k, 7) with frame t carrying the k actions that led to it, no_action, state, done and task.
        `shuffle`: every clip gets another clip's controls (text: one instruction for all), so that nothing but
        chance links a control to its frames."""
        rng = np.random.default_rng([seed, step])
        k = frame_skip
        episode = self.episodes(rng, batch_size, (window - 1) * k)
        controls = episode["controls"]
        if shuffle and self.kind != "text":
            controls = controls[np.roll(np.arange(batch_size), 1)]
        actions = np.zeros((batch_size, window, k, ACTION_DIM), np.float32)
        if self.kind == "text":
            names = list(INSTRUCTIONS)
            task = [names[0] if shuffle else names[c] for c in controls]
        else:
            actions[:, 1:] = controls.reshape(batch_size, window - 1, k, ACTION_DIM)
            task = ["move the square"] * batch_size
        no_action = np.zeros((batch_size, window), bool)
        no_action[:, 0] = True
        return {
            "tokens": torch.from_numpy(episode["tokens"][:, ::k]).long(),
            "anchor": torch.from_numpy(episode["tokens"][:, 0]).long(),  # the episode's first frame (clean)
            "actions": torch.from_numpy(actions),
            "no_action": torch.from_numpy(no_action),
            "state": torch.from_numpy(episode["states"][:, ::k]),
            "done": torch.zeros(batch_size, window),
            "task": task,
        }

    def action_stats(self, seed: int = 0, n: int = 4096) -> dict[str, np.ndarray]:
        """The actions' statistics as LeRobot computes them for a dataset (dataset.meta.stats["action"])."""
        if self.kind == "text":
            raise ValueError("the text world has instructions, not actions")
        actions = self.random_controls(np.random.default_rng(seed), n, 1)[:, 0]
        return {"mean": actions.mean(0), "std": actions.std(0), "min": actions.min(0), "max": actions.max(0)}

    def state_stats(self) -> dict[str, np.ndarray]:
        """The states' statistics: a cell drawn uniformly."""
        cells = np.arange(self.cells, dtype=np.float64)
        return {"mean": np.full(STATE_DIM, cells.mean()), "std": np.full(STATE_DIM, cells.std())}


@torch.no_grad()
def retrieval(model, world: SyntheticWorld, starts: int = 32, K: int = 4, horizon: int = 4, seed: int = 1234):
    """Retrieval accuracy of the model's rollouts among K controls from each of `starts` starts (K = 2 for text,
    one rollout per instruction) over `horizon` model frames (each the model's frame_skip control steps), and the
    rollouts (starts, K, horizon, S) with their real futures."""
    rng = np.random.default_rng(seed)
    K = len(INSTRUCTIONS) if world.kind == "text" else K
    k = model.config.frame_skip
    background, position = world.random_starts(rng, starts, horizon * k)
    if world.kind == "text":
        controls = np.tile(np.arange(K), starts)
    else:
        controls = world.random_controls(rng, starts * K, horizon * k)
    starts_K = (np.repeat(background, K, 0), np.repeat(position, K, 0))
    episodes = world.episodes(rng, starts * K, horizon * k, controls=controls, starts=starts_K)
    real = episodes["tokens"][:, ::k]
    device = next(model.parameters()).device
    prompt = torch.from_numpy(real[:, :1]).to(device)
    first = torch.from_numpy(episodes["states"][:, :1]).to(device)
    if world.kind == "text":
        names = list(INSTRUCTIONS)
        rollout = model.generate(prompt, horizon, instructions=[names[c] for c in controls], states=first).tokens
    else:
        rollout = model.generate(prompt, horizon, actions=torch.from_numpy(controls).to(device), states=first).tokens
    rollout = rollout.cpu().numpy().reshape(starts, K, horizon, -1)
    future = real[:, 1:].reshape(starts, K, horizon, -1)
    # agreement[s, i, j]: rollout i of start s against real future j
    agreement = (rollout[:, :, None] == future[:, None]).mean(axis=(3, 4))
    accuracy = float(np.mean([retrieval_accuracy(a) for a in agreement]))
    return accuracy, rollout, future


@torch.no_grad()
def drift(model, world: SyntheticWorld, starts: int = 64, horizon: int = 32, seed: int = 4321) -> dict[str, list]:
    """How a motion rollout keeps its world over `horizon` frames, well past the model's window: per generated
    frame, the share of the background's cells (where neither the real square nor the rollout's is) that keep the
    real token, of those the square has just uncovered (their token read from memory: the window, or an anchor),
    and the share of rollouts with the square drawn whole where the real one is."""
    if world.kind == "text":
        raise ValueError("drift() rolls a world out under actions; the text world has instructions")
    rng = np.random.default_rng(seed)
    episodes = world.episodes(rng, starts, horizon)
    device = next(model.parameters()).device
    real = episodes["tokens"]  # (n, horizon + 1, S)
    rollout = (
        model.generate(
            torch.from_numpy(real[:, :1]).to(device),
            horizon,
            actions=torch.from_numpy(episodes["controls"]).to(device),
            states=torch.from_numpy(episodes["states"][:, :1]).to(device),
        )
        .tokens.cpu()
        .numpy()
    )
    future, square = real[:, 1:], world.square_token
    background = (future != square) & (rollout != square)
    uncovered = background & (real[:, :-1] == square)

    def kept(cells):
        return (((rollout == future) & cells).sum((0, 2)) / np.maximum(cells.sum((0, 2)), 1)).tolist()

    drawn = ((rollout == square) | (future != square)).all(2).mean(0)
    return {"background": kept(background), "uncovered": kept(uncovered), "square": drawn.tolist()}


def world_model(
    world: SyntheticWorld, window: int, seed: int = 0, normalize_actions: bool = True, **overrides
) -> STWorldModel:
    """The tiny preset (its architecture and control path) sized to the world's grid, a frame per action (the
    worlds move one cell per action), its initial weights drawn from `seed`; the actions normalised by the world's
    statistics unless `normalize_actions` is off; the square's cell as its state; any other config field as
    `overrides`."""
    if normalize_actions and world.kind != "text":
        stats = world.action_stats()
        overrides.update(action_mean=stats["mean"].tolist(), action_std=stats["std"].tolist())
    stats = world.state_stats()
    overrides = (
        dict(state_dim=STATE_DIM, state_mean=stats["mean"].tolist(), state_std=stats["std"].tolist()) | overrides
    )
    torch.manual_seed(seed)
    config = TinyWorldModelConfig(
        control="text" if world.kind == "text" else "action",
        action_dim=ACTION_DIM,
        frame_skip=1,
        n_cameras=1,
        tokens_per_side=world.grid,
        vocab_size=world.vocab_size,
        window=window,
        prompt_frames=1,
        **overrides,
    )
    return STWorldModel(config)


def train_on_world(
    model,
    world: SyntheticWorld,
    steps: int,
    batch_size: int = 16,
    lr: float = 1e-3,
    warmup_steps: int = 50,
    seed: int = 0,
    shuffle: bool = False,
    eval_every: int = 0,
    minutes: float | None = None,
    on_eval=None,
    until: float | None = None,
) -> list[dict]:
    """Train `model` on fresh batches of `world` (AdamW, linear warm-up), for `steps` steps or `minutes` of
    training time, whichever ends first, or once retrieval reached `until` at two evaluations in a row. Every
    `eval_every` steps (and at the end) measure retrieval; the clock stops while it does. Returns the curve:
    {"step", "minutes", "retrieval", "loss"} per evaluation, each updated with what `on_eval(point, model)`
    returns (other measures of the same model), also outside the clock."""
    optimizer = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=0.01)
    schedule = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda s: min(1.0, (s + 1) / warmup_steps))
    curve, trained_seconds, losses = [], 0.0, []

    def evaluate(step):
        model.eval()
        accuracy = retrieval(model, world)[0]
        model.train()
        point = {"step": step, "minutes": trained_seconds / 60, "retrieval": accuracy, "loss": float(np.mean(losses))}
        if on_eval is not None:
            point.update(on_eval(point, model) or {})
            model.train()
        curve.append(point)
        losses.clear()

    model.train()
    for step in range(1, steps + 1):
        tic = time.perf_counter()
        batch = world.training_batch(
            step, batch_size, model.config.window, seed=seed, shuffle=shuffle, frame_skip=model.config.frame_skip
        )
        loss, _ = model(batch)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        optimizer.step()
        schedule.step()
        trained_seconds += time.perf_counter() - tic
        losses.append(loss.item())
        out_of_time = minutes is not None and trained_seconds >= 60 * minutes
        if step == steps or out_of_time or (eval_every and step % eval_every == 0):
            evaluate(step)
        solved = until is not None and len(curve) >= 2 and min(p["retrieval"] for p in curve[-2:]) >= until
        if out_of_time or solved:
            break
    model.eval()
    return curve
