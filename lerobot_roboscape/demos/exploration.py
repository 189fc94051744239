"""Exploratory episodes: the planner's plan, with actions that leave it, so the action world model sees what
actions do (the paper collects suboptimal trajectories "to enable a more comprehensive learning of the action
space").

A planner episode barely needs its actions: the previous frames already say where the arm goes next. These kinds
break that, each in its own way, while the plan still brings the arm back to the task:
- *noisy*: Gaussian noise on every action of the plan, at a level drawn once per episode;
- *excursion*: now and then the arm leaves for a random point 5-15 cm away (the gripper held), then the plan
  resumes and brings it back;
- *random*: now and then a stretch of uniformly random actions over the whole [-1, 1] range, gripper included.

Exploratory episodes train the action world model and nothing that imitates: `roboscape-collect --kinds=[...]`
writes them to a dataset of their own, apart from the demonstrations that SFT, lerobot-train's normalisation
statistics and the text world model read.
"""

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from lerobot_roboscape.demos.planner import Waypoint, WaypointFollower, plan_episode
from lerobot_roboscape.tasks.base import RoboscapeTabletopEnv

EXPLORATORY_KINDS = ("noisy", "excursion", "random")


@dataclass
class ExplorationConfig:
    """How far exploratory episodes leave the plan.

    Args:
        noise_std: (low, high) of the per-episode std of the noise on every action dimension (normalised units).
        excursion_prob: chance per control step, while on the plan, of leaving it on an excursion.
        excursion_distance: (low, high) distance (m) of an excursion's target from the TCP.
        excursion_steps: (low, high) control steps an excursion lasts at most.
        random_prob: chance per control step, while on the plan, of starting a stretch of random actions.
        random_steps: (low, high) control steps a random stretch lasts.
    """

    noise_std: tuple[float, float] = (0.1, 0.5)
    excursion_prob: float = 0.05
    excursion_distance: tuple[float, float] = (0.05, 0.15)
    excursion_steps: tuple[int, int] = (4, 12)
    random_prob: float = 0.05
    random_steps: tuple[int, int] = (4, 16)


class ExploringFollower:
    """A `WaypointFollower` whose actions depart from its plan as the episode's `kind` says; same interface."""

    def __init__(self, plan: WaypointFollower, kind: str, rng: np.random.Generator, cfg: ExplorationConfig):
        if kind not in EXPLORATORY_KINDS:
            raise ValueError(f"Unknown exploratory kind {kind!r}; expected one of {EXPLORATORY_KINDS}")
        self.plan, self.kind, self.rng, self.cfg = plan, kind, rng, cfg
        self.noise_std = float(rng.uniform(*cfg.noise_std)) if kind == "noisy" else 0.0
        self.detour: WaypointFollower | None = None  # the excursion under way
        self.steps_left = 0  # of the excursion or random stretch under way
        self.departures = 0

    @property
    def done(self) -> bool:
        return self.plan.done and self.steps_left == 0

    @property
    def skipped(self) -> int:
        return self.plan.skipped

    def act(self, tcp_pos: np.ndarray, tcp_quat_wxyz: np.ndarray) -> np.ndarray:
        if self.steps_left == 0 and not self.plan.done:
            self._maybe_depart(tcp_pos, tcp_quat_wxyz)
        if self.steps_left > 0:
            self.steps_left -= 1
            if self.kind == "random":
                return self.rng.uniform(-1.0, 1.0, 7).astype(np.float32)
            return self.detour.act(tcp_pos, tcp_quat_wxyz)
        action = self.plan.act(tcp_pos, tcp_quat_wxyz)
        if self.kind == "noisy":
            action = np.clip(action + self.rng.normal(0.0, self.noise_std, action.shape), -1.0, 1.0)
        return action.astype(np.float32)

    def _maybe_depart(self, tcp_pos: np.ndarray, tcp_quat_wxyz: np.ndarray) -> None:
        cfg = self.cfg
        if self.kind == "random" and self.rng.random() < cfg.random_prob:
            self.steps_left = int(self.rng.integers(cfg.random_steps[0], cfg.random_steps[1] + 1))
            self.departures += 1
        elif self.kind == "excursion" and self.rng.random() < cfg.excursion_prob:
            direction = self.rng.normal(size=3)
            direction[2] = abs(direction[2])  # away from the table, not into it
            target = tcp_pos + direction / np.linalg.norm(direction) * self.rng.uniform(*cfg.excursion_distance)
            gripper = self.plan.waypoints[self.plan.index].gripper
            # The follower rotates relative to its start orientation: hold the current one.
            current = Rotation.from_quat(tcp_quat_wxyz, scalar_first=True)
            hold = (current * self.plan.start_rotation.inv()).as_rotvec()
            self.detour = WaypointFollower(
                [Waypoint(target, gripper, rotation=hold, essential=False)],
                self.plan.start_rotation.as_quat(scalar_first=True),
                max_step=self.plan.max_step,
            )
            self.steps_left = int(self.rng.integers(cfg.excursion_steps[0], cfg.excursion_steps[1] + 1))
            self.departures += 1


def explore_episode(
    env: RoboscapeTabletopEnv, kind: str, rng: np.random.Generator, cfg: ExplorationConfig | None = None
) -> ExploringFollower:
    """An exploring follower of the optimal plan for the env's freshly reset episode."""
    return ExploringFollower(plan_episode(env, "optimal", rng), kind, rng, cfg or ExplorationConfig())
