"""The goal bank of `roboscape_wm`: the goal frame of each episode start, made once and kept. The text world model
makes it from the start under the start's instruction, frame after frame, until its done signal crosses theta
(the frame there is the goal; when it never does, the last frame generated); or it is the dataset episode's own
last frame (goal_source="dataset_last_frame"). With a goal file, the goals outlive the process (safetensors, with
the settings they were made with), so PPO's runs share one generation made before their clocks start."""

import json
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import torch

from lerobot_roboscape.io.console import say_once
from lerobot_roboscape.io.tensor_files import load_tensors, save_tensors
from lerobot_roboscape.io.weights import weights_digest
from lerobot_roboscape.world_model.goals import generate_goals
from lerobot_roboscape.world_model.modeling_world_model import STWorldModel
from roboscape_core.errors import InvalidInputError

logger = logging.getLogger(__name__)
# Every env made over the same starts generates their goals again: an episode's warning is said once.
say_once(__name__)
GOAL_SOURCES = ("text_model", "dataset_last_frame")
# Goals are generated in batches of this fixed size (padded), so a start's goal never depends on which other
# starts shared its batch: the same seed gives the same goals in a fresh, a resumed or a longer run.
GOAL_BATCH = 8


def goal_generation_seconds(path: Path) -> float | None:
    """Seconds the text model spent generating the goals of a goal file (`goal_file`), when it recorded them."""
    if not Path(path).is_file():
        return None
    seconds = load_tensors(path, "the goal bank (--env.goal_file)")[0].get("seconds")
    return None if seconds is None else float(seconds)


class Goal(NamedTuple):
    tokens: torch.Tensor  # (S,)
    reached: bool  # the text model crossed theta (else its last generated frame is the goal)
    steps: int  # frames generated up to the goal (0: the dataset's own last frame)
    state: torch.Tensor | None = None  # (D,) the robot's state at the goal, where the text model carries one


@dataclass
class EpisodeStart:
    episode_index: int
    task: str
    first_tokens: torch.Tensor  # (S,) the frame an episode from this start begins with
    last_tokens: torch.Tensor  # (S,)
    facts: dict
    horizon: int  # steps of an episode from this start
    frame: int = 0  # where in its recorded episode the start is (a branched start: later than 0)
    episode_first_tokens: torch.Tensor | None = None  # (S,) its episode's first frame, for a branched start
    first_state: torch.Tensor | None = None  # (D,) the robot's state in the first frame
    last_state: torch.Tensor | None = None  # (D,)
    episode_first_state: torch.Tensor | None = None  # (D,) in its episode's first frame, for a branched start

    @property
    def family(self) -> str | None:
        """Its episode's task family, as recorded (None for a dataset without roboscape facts)."""
        return self.facts.get("task_family")

    @property
    def scene(self) -> str | None:
        return self.facts.get("scene")

    @property
    def goal_prompt(self) -> torch.Tensor:
        """The frame the start's goal is generated from: its episode's first, so every start of an episode shares
        the episode's goal."""
        return self.first_tokens if self.episode_first_tokens is None else self.episode_first_tokens

    @property
    def goal_prompt_state(self) -> torch.Tensor | None:
        return self.first_state if self.episode_first_state is None else self.episode_first_state


class GoalBank:
    """Goals of the starts of one env: `goals_for` (cached, as PPO's episodes use them), `generate` (made now, as
    a start from given frames needs), `use_file` (a goal file read, completed and written back)."""

    def __init__(
        self,
        config,
        text_model: STWorldModel | None,
        frame_skip: int,
        device: str,
        done_of: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
        autocast: Callable,
        settings: dict,
    ):
        """config: the env's `RoboscapeWorldModelEnvConfig` (goal_source, theta, max_goal_steps); done_of: the env's
        done source, read on generated frames; settings: what a generated goal depends on besides its start."""
        self.config, self.text_model, self.frame_skip, self.device = config, text_model, frame_skip, device
        self.done_of, self.autocast, self.settings = done_of, autocast, settings
        self.cache: dict[int, Goal] = {}

    @torch.no_grad()
    def goals_for(self, starts: list[EpisodeStart]) -> tuple[torch.Tensor, list[bool]]:
        """Goal tokens (B, S) of these starts, generated once per start and cached; and whether the text model
        crossed theta (when it never does, the last generated frame is the goal). `goal_of` has the details."""
        missing = [s for s in {s.episode_index: s for s in starts}.values() if s.episode_index not in self.cache]
        if missing and self.config.goal_source == "dataset_last_frame":
            for s in missing:
                self.cache[s.episode_index] = Goal(s.last_tokens, True, 0, s.last_state)
        elif missing:
            self._fill(missing)
        goals = [self.cache[s.episode_index] for s in starts]
        return torch.stack([g.tokens for g in goals]), [g.reached for g in goals]

    def goal_of(self, start: EpisodeStart) -> Goal:
        self.goals_for([start])
        return self.cache[start.episode_index]

    def use_file(self, path: Path, starts: list[EpisodeStart]) -> None:
        """Read the goals of `path`, generate every start's missing one and write them all back (atomically). The
        file records the text model's weights beside the settings, so that a model retrained in the same folder does
        not read the goals of the one it replaced (a retrained tokenizer means a retrained text model too). Hashed
        here, once per file, not at every env's start."""
        model = self.text_model
        settings = self.settings | {"weights": model and weights_digest(model, vars(model.config))}
        if path.is_file():
            metadata, tensors = load_tensors(path, "the goal bank (--env.goal_file)", ("settings",), self.device)
            made_with = json.loads(metadata["settings"])
            if made_with != settings:
                differ = {k: made_with.get(k) for k in settings if made_with.get(k) != settings[k]}
                raise InvalidInputError(
                    f"goal file {path} was made with other settings {differ}; delete it or choose another "
                    "--env.goal_file"
                )
            indices, tokens = tensors["episode_index"].tolist(), tensors["tokens"]
            reached, steps = tensors["reached"].tolist(), tensors["steps"].tolist()
            states = tensors.get("states")
            for i, index in enumerate(indices):
                self.cache[index] = Goal(
                    tokens[i], bool(reached[i]), int(steps[i]), None if states is None else states[i]
                )
        missing = [s for s in {s.episode_index: s for s in starts}.values() if s.episode_index not in self.cache]
        if not missing:
            return
        started = time.perf_counter()
        self._fill(missing)
        seconds = time.perf_counter() - started
        logger.info("generated %d goals in %.0f s into %s", len(missing), seconds, path)
        seconds += goal_generation_seconds(path) or 0.0
        goals = sorted(self.cache.items())
        tensors = {
            "episode_index": torch.tensor([index for index, _ in goals]),
            "tokens": torch.stack([g.tokens for _, g in goals]).cpu(),
            "reached": torch.tensor([g.reached for _, g in goals]),
            "steps": torch.tensor([g.steps for _, g in goals]),
        }
        if all(g.state is not None for _, g in goals):
            tensors["states"] = torch.stack([g.state for _, g in goals]).cpu()
        save_tensors(path, tensors, {"settings": json.dumps(settings), "seconds": str(seconds)})

    def _fill(self, starts: list[EpisodeStart]) -> None:
        for s, goal in zip(starts, self.generate(starts), strict=True):
            self.cache[s.episode_index] = goal

    @torch.no_grad()
    def generate(self, starts: list[EpisodeStart]) -> list[Goal]:
        """The text model's goal of each start under its `task`, generated now (not cached: a start given another
        instruction gets the goal of that instruction)."""
        goals = []
        with self.autocast():
            for chunk in range(0, len(starts), GOAL_BATCH):
                goals += self._generate_batch(starts[chunk : chunk + GOAL_BATCH])
        return goals

    def _generate_batch(self, starts: list[EpisodeStart]) -> list[Goal]:
        padded = starts + [starts[-1]] * (GOAL_BATCH - len(starts))
        states = None
        if self.text_model.config.state:
            states = torch.stack([s.goal_prompt_state for s in padded])
        goals = generate_goals(
            self.text_model,
            torch.stack([s.goal_prompt for s in padded]),
            [s.task for s in padded],
            self.config.theta,
            self.frame_skip,
            self.config.max_goal_steps,
            states,
            self.done_of,
        )
        for i, s in enumerate(starts):
            if not goals.reached[i]:
                logger.warning(
                    "text world model: done stayed below theta=%.2f for %d control steps from episode %d (%r); "
                    "its last generated frame is the goal",
                    self.config.theta,
                    self.config.max_goal_steps,
                    s.episode_index,
                    s.task,
                )
        return [
            Goal(
                goals.tokens[i],
                bool(goals.reached[i]),
                int(goals.steps[i]),
                None if goals.states is None else goals.states[i],
            )
            for i in range(len(starts))
        ]
