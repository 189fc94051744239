"""The text model's goals: from a start, frames generated under its instruction until the done signal crosses theta
(that frame is the goal; when it never does, the last one generated). `generate_goals` is the one place a goal is
made: `roboscape_wm`'s goal bank makes PPO's goals with it, and `goal_summary` judges the goals of held-out starts
as the text model trains (its held-out curve, `--heldout_goals` of `roboscape-train-wm`): how often the done fires
within the family's horizon, and whether the goal is nearer the episode's real final frame than its start is."""

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from lerobot_roboscape.dataset.reader import (
    episode_facts,
    episode_indices,
    family_horizons,
    read_frames,
    read_states,
    successful_episodes,
)
from lerobot_roboscape.io.tensor_files import load_tensors, save_tensors
from lerobot_roboscape.tokenizer.modeling_tokenizer import VisualTokenizer
from lerobot_roboscape.tokenizer.similarity import TokenizerPerceptualDistance, frame_distance
from lerobot_roboscape.world_model.rollout import Rollout
from roboscape_core.errors import InvalidInputError


@dataclass
class Goals:
    tokens: torch.Tensor  # (B, S) the goal frames
    states: torch.Tensor | None  # (B, D) the robot's states there, where the model carries one
    reached: torch.Tensor  # (B,) bool: the done crossed theta
    steps: torch.Tensor  # (B,) control steps generated up to the goal
    done_max: torch.Tensor  # (B,) the highest done along the way: what a threshold for this model is chosen from


@torch.no_grad()
def generate_goals(
    model,
    prompt_BS: torch.Tensor,
    instructions: list[str],
    theta: float,
    frame_skip: int,
    max_steps: int,
    states_BD: torch.Tensor | None = None,
    done_of: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None = None,
) -> Goals:
    """Goals of B starts (prompt frames (B, S), their states (B, D) where the text model carries them) under their
    instructions, generated for at most `max_steps` control steps (a frame per `frame_skip`). `done_of(frame,
    model_done)`: the done source read on each generated frame (default: the text model's own head)."""
    control = model.encode_control(instructions=instructions)
    prompt = prompt_BS[:, None]
    states = None if states_BD is None or not model.config.state else states_BD[:, None].to(prompt.device)
    rollout = Rollout.start(model, prompt, control, states=states)
    B = prompt.shape[0]
    goal, goal_state = prompt[:, 0].clone(), None if states is None else states[:, 0].clone()
    reached = torch.zeros(B, dtype=torch.bool, device=prompt.device)
    done_max = torch.zeros(B, device=prompt.device)
    max_frames = -(-max_steps // frame_skip)
    steps = torch.full((B,), max_frames * frame_skip, device=prompt.device)
    for frame_index in range(1, max_frames + 1):
        frame, done = rollout.predict_next_frame(control)
        done = done if done_of is None else done_of(frame, done)
        done_max = torch.maximum(done_max, done.float())
        goal[~reached] = frame[~reached]  # the latest frame until theta is crossed
        if goal_state is not None:
            goal_state[~reached] = rollout.state[~reached]
        newly = (done >= theta) & ~reached
        steps[newly] = frame_index * frame_skip
        reached |= newly
        if reached.all():
            break
    return Goals(goal, goal_state, reached, steps, done_max)


@dataclass
class GoalStart:
    """A held-out start of a goal set: its episode's first and last frames (tokens (S,)), first state (D,),
    instruction, its family's horizon and whether the episode succeeded."""

    episode_index: int
    task: str
    horizon: int
    success: bool
    first: torch.Tensor
    last: torch.Tensor
    first_state: torch.Tensor


def read_goal_starts(dataset, tokenizer: VisualTokenizer, keep: int | None = None) -> list[GoalStart]:
    """The starts of a held-out dataset (at most `keep`, spread over its episodes): its episodes' first frames, with
    their last frames to judge the goals by."""
    indices = episode_indices(dataset)
    if keep is not None:
        indices = [indices[i] for i in np.unique(np.linspace(0, len(indices) - 1, keep).round().astype(int))]
    horizons, successful = family_horizons(dataset), set(successful_episodes(dataset))
    starts = []
    for index in indices:
        meta = dataset.meta.episodes[index]
        family = episode_facts(dataset, index).get("task_family")
        tokens = tokenizer.encode_frames(list(read_frames(dataset, index, [0, -1]).values())).cpu()
        state = torch.from_numpy(read_states(dataset, index, [0])[0])
        horizon = horizons.get(family, horizons[None])
        starts.append(GoalStart(index, meta["tasks"][0], horizon, index in successful, tokens[0], tokens[1], state))
    if not starts:
        raise InvalidInputError(f"{dataset.root} has no episode to start a goal from")
    return starts


GOAL_STARTS_FIELDS = ("first", "last", "first_state")


def save_goal_starts(starts: list[GoalStart], path: str | Path) -> None:
    """A goal set in one safetensors file: what the text model's curve reads without the datasets' videos."""
    tensors = {name: torch.stack([getattr(s, name) for s in starts]).contiguous() for name in GOAL_STARTS_FIELDS}
    facts = [
        {"episode_index": s.episode_index, "task": s.task, "horizon": s.horizon, "success": s.success} for s in starts
    ]
    save_tensors(path, tensors, {"starts": json.dumps(facts)})


def load_goal_starts(path: str | Path, device="cpu") -> list[GoalStart]:
    """The starts `save_goal_starts` wrote."""
    metadata, tensors = load_tensors(path, "save_goal_starts", ("starts",), device)
    return [
        GoalStart(
            f["episode_index"], f["task"], f["horizon"], f["success"], *(tensors[n][i] for n in GOAL_STARTS_FIELDS)
        )
        for i, f in enumerate(json.loads(metadata["starts"]))
    ]


@torch.no_grad()
def goal_summary(
    model,
    tokenizer: VisualTokenizer,
    distance: TokenizerPerceptualDistance,
    starts: list[GoalStart],
    theta: float,
    frame_skip: int,
    batch: int = 8,
) -> dict[str, float]:
    """The text model's goals from `starts` (`batch` at a time), generated up to each start's horizon: the share
    whose done crossed theta within it (`goal_reached`), the median control steps to those goals over the horizon
    (`goal_steps_share`: near 0, the done fires at once and the goal is the start), the median highest done
    (`goal_done_max`), and over the successful episodes the share whose goal is nearer the real final frame than the
    start is, by the tokenizer's perceptual distance (`distance`, made once by the caller: the reward's similarity
    offline; `goal_nearer_final`)."""
    device = next(model.parameters()).device
    n_cameras = model.config.n_cameras
    reached, steps_share, done_max, nearer = [], [], [], []
    starts = sorted(starts, key=lambda s: s.horizon)  # a batch of one family generates to its own horizon
    for chunk in range(0, len(starts), batch):
        part = starts[chunk : chunk + batch]
        goals = generate_goals(
            model,
            torch.stack([s.first for s in part]).to(device),
            [s.task for s in part],
            theta,
            frame_skip,
            max(s.horizon for s in part),
            torch.stack([s.first_state for s in part]),
        )
        horizons = torch.tensor([s.horizon for s in part], device=device)
        within = goals.reached & (goals.steps <= horizons)
        reached += within.tolist()
        steps_share += (goals.steps / horizons)[within].tolist()
        done_max += goals.done_max.tolist()
        images = [
            tokenizer.decode_views(t.to(device), n_cameras)
            for t in (torch.stack([s.first for s in part]), goals.tokens, torch.stack([s.last for s in part]))
        ]
        to_start = frame_distance(distance, images[2], images[0])
        to_goal = frame_distance(distance, images[2], images[1])
        nearer += [bool(g < s) for g, s, start in zip(to_goal, to_start, part, strict=True) if start.success]
    return {
        "goal_reached": float(np.mean(reached)),
        "goal_steps_share": float(np.median(steps_share)) if steps_share else None,
        "goal_done_max": float(np.median(done_max)),
        "goal_nearer_final": float(np.mean(nearer)) if nearer else None,
    }
