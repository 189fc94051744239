"""Waypoint planner for the four task families, and a follower that turns waypoints into 7-D actions.

The paper plans with MPLib, but mani-skill 3.0.1 pins mplib 0.1.1, which segfaults under NumPy 2 (which
LeRobot needs). The tabletop is free of obstacles above the table, so straight Cartesian segments between
waypoints, tracked by the `pd_ee_delta_pose` controller, give the same kind of trajectory: an *optimal* one
visits only the essential waypoints; a *suboptimal* one adds detours with position/rotation noise, interpolated
points and small perturbations near grasp and place (paper, section 4.1). A *failed* one is a realistic attempt
that misses: the world model's done head has to see what failure looks like, not only successes.
"""

from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial.transform import Rotation

from lerobot_roboscape.tasks.base import RoboscapeTabletopEnv

GRIPPER_OPEN, GRIPPER_CLOSED = 1.0, -1.0
KINDS = ("optimal", "suboptimal", "failed")  # of plans; recorded with each episode as its "kind"
# pd_ee_delta_pose maps [-1, 1] to +-0.1 m and +-0.1 rad per control step. Its rotation is scaled by the
# controller's `rot_lower` (-0.1), so a positive action turns the negative way.
POS_SCALE, ROT_SCALE = 0.1, -0.1


@dataclass
class Waypoint:
    """A TCP target in the world frame.

    Args:
        position: (3,) xyz.
        gripper: command held while moving to and waiting at this waypoint (+1 open, -1 closed).
        rotation: extra rotation (rotation vector, rad, world frame) relative to the start orientation.
        hold: control steps to wait once reached (lets the gripper close or open).
        tolerance: position error (m) at which the waypoint counts as reached.
        essential: False for the detours a suboptimal trajectory adds.
    """

    position: np.ndarray
    gripper: float
    rotation: np.ndarray = field(default_factory=lambda: np.zeros(3))
    hold: int = 0
    tolerance: float = 0.01
    essential: bool = True


@dataclass
class SuboptimalConfig:
    """How a suboptimal trajectory departs from the optimal one.

    Args:
        detour_prob: chance of a detour waypoint before each essential move.
        detour_noise: std (m) of the detour's offset from the segment's midpoint.
        rotation_noise: std (rad) of the detour's rotation.
        interpolate_prob: chance of splitting a segment with noisy intermediate points.
        perturb_prob: chance of a near-miss waypoint before a grasp or a release.
        perturb_noise: std (m) of that near miss.
    """

    detour_prob: float = 0.5
    detour_noise: float = 0.06
    rotation_noise: float = 0.25
    interpolate_prob: float = 0.4
    perturb_prob: float = 0.6
    perturb_noise: float = 0.015


@dataclass
class FailureConfig:
    """How a failed attempt departs from the optimal plan: it misses the object, or it falls short.

    Args:
        miss_prob: chance of a miss (the fingers close on air beside the object, or the paddle passes beside it)
            rather than falling short (the object put down early, or a push stopped early).
        miss_clearance: (low, high) distance (m) from the object's outline to the fingers' centre line in a miss.
        release_fraction: (low, high) share of the carry made before the object is put down; the target is at
            least 0.15 m away, so the object rests well outside it.
        push_fraction: (low, high) share of the push stroke made before stopping; the object then moves less than
            half the required distance.
    """

    miss_prob: float = 0.5
    miss_clearance: tuple[float, float] = (0.025, 0.04)
    release_fraction: tuple[float, float] = (0.0, 0.3)
    push_fraction: tuple[float, float] = (0.15, 0.45)


def essential_waypoints(env: RoboscapeTabletopEnv) -> list[Waypoint]:
    """The shortest plan for the env's current episode."""
    obj = env.obj.pose.p[0].cpu().numpy()
    spec = env.scene_spec.object
    grasp_z = max(obj[2], 0.015)
    if env.family in ("pick_place", "move_to_aim"):
        if env.family == "pick_place":
            target = env.container.pose.p[0].cpu().numpy()
            release_z = env.scene_spec.container.wall_height + spec.half_height + 0.025
        else:
            target = env.carpet.pose.p[0].cpu().numpy()
            release_z = spec.half_height + 0.015
        return [
            Waypoint(obj + [0, 0, 0.1], GRIPPER_OPEN, tolerance=0.02),
            Waypoint(np.array([obj[0], obj[1], grasp_z]), GRIPPER_OPEN, tolerance=0.006),
            Waypoint(np.array([obj[0], obj[1], grasp_z]), GRIPPER_CLOSED, hold=6, tolerance=0.01),
            Waypoint(np.array([obj[0], obj[1], 0.15]), GRIPPER_CLOSED, tolerance=0.02),
            Waypoint(np.array([target[0], target[1], 0.15]), GRIPPER_CLOSED, tolerance=0.015),
            Waypoint(np.array([target[0], target[1], release_z]), GRIPPER_CLOSED, tolerance=0.01),
            Waypoint(np.array([target[0], target[1], release_z]), GRIPPER_OPEN, hold=4, tolerance=0.02),
            Waypoint(np.array([target[0], target[1], release_z + 0.1]), GRIPPER_OPEN, tolerance=0.03),
        ]
    if env.family in ("push", "pull"):
        # The closed fingers act as a paddle behind the object (on the far side when pulling).
        direction = np.array([env.direction, 0.0, 0.0])
        reach = spec.size[0] + 0.025
        behind = np.array([obj[0], obj[1], grasp_z]) - direction * reach
        goal = env.goal_xy[0].cpu().numpy()
        end = np.array([goal[0], goal[1], grasp_z]) - direction * (reach - 0.015)
        return [
            Waypoint(behind + [0, 0, 0.1], GRIPPER_CLOSED, tolerance=0.02),
            Waypoint(behind, GRIPPER_CLOSED, tolerance=0.008),
            Waypoint(end, GRIPPER_CLOSED, tolerance=0.01),
            Waypoint(end + [0, 0, 0.1], GRIPPER_CLOSED, tolerance=0.03),
        ]
    raise ValueError(f"No planner for task family {env.family!r}")


def make_suboptimal(plan: list[Waypoint], rng: np.random.Generator, cfg: SuboptimalConfig) -> list[Waypoint]:
    """Insert detours, interpolated points and near misses between the essential waypoints."""
    out: list[Waypoint] = []
    previous = plan[0].position
    for waypoint in plan:
        moving = np.linalg.norm(waypoint.position - previous) > 0.03
        # Near the table a sideways detour would sweep the object away: vary only the moves up high.
        moving = moving and min(previous[2], waypoint.position[2]) >= 0.05
        if moving and rng.random() < cfg.detour_prob:
            midpoint = (previous + waypoint.position) / 2 + rng.normal(0, cfg.detour_noise, 3)
            midpoint[2] = max(midpoint[2] + 0.05, 0.06)  # detours go up, away from the table
            rotation = rng.normal(0, cfg.rotation_noise, 3) * [0.4, 0.4, 1.0]
            out.append(
                Waypoint(
                    midpoint, out[-1].gripper if out else waypoint.gripper, rotation, tolerance=0.03, essential=False
                )
            )
        elif moving and rng.random() < cfg.interpolate_prob:
            for fraction in sorted(rng.uniform(0.2, 0.8, size=rng.integers(1, 3))):
                point = previous + fraction * (waypoint.position - previous) + rng.normal(0, 0.01, 3)
                point[2] = max(point[2], waypoint.position[2], 0.02)
                out.append(
                    Waypoint(point, out[-1].gripper if out else waypoint.gripper, tolerance=0.02, essential=False)
                )
        if waypoint.hold and rng.random() < cfg.perturb_prob:
            # A near miss just above the grasp/release point, then the real one.
            near = waypoint.position + rng.normal(0, cfg.perturb_noise, 3) * [1, 1, 0.5]
            near[2] = max(near[2], waypoint.position[2]) + 0.03  # above the object: a near miss, not a knock
            carried = out[-1].gripper if out else waypoint.gripper
            out.append(Waypoint(near, carried, rng.normal(0, 0.08, 3), tolerance=0.008, essential=False))
        out.append(waypoint)
        previous = waypoint.position
    return out


def make_failed(
    plan: list[Waypoint], rng: np.random.Generator, family: str, object_radius: float, cfg: FailureConfig
) -> list[Waypoint]:
    """A perturbed `essential_waypoints` plan of `family` that does not accomplish the task but otherwise moves like
    a real attempt. `object_radius`: the object's outline seen from above (m)."""
    miss = rng.random() < cfg.miss_prob
    # Misses are sideways in y, across the push and across the fingers, which close along x at the rest pose.
    shift = np.array([0.0, rng.choice([-1.0, 1.0]) * (object_radius + rng.uniform(*cfg.miss_clearance)), 0.0])
    if family in ("pick_place", "move_to_aim"):
        grasp = next(i for i, w in enumerate(plan) if w.gripper == GRIPPER_CLOSED)
        if miss:  # the fingers go down and close beside the object, lift and carry on as if holding it
            return [replace(w, position=w.position + shift) if i <= grasp + 1 else w for i, w in enumerate(plan)]
        # The same place moves, at a point part of the way: put down gently rather than dropped from the carry
        # height, from which a ball would bounce and could roll over the target.
        lift, carry_end = plan[grasp + 1].position, plan[grasp + 2].position
        short = (rng.uniform(*cfg.release_fraction) - 1) * (carry_end - lift)
        return plan[: grasp + 2] + [replace(w, position=w.position + short) for w in plan[grasp + 2 :]]
    if family in ("push", "pull"):
        if miss:  # the paddle passes beside the object
            return [replace(w, position=w.position + shift) for w in plan]
        approach, behind, end, _ = plan
        stop = behind.position + rng.uniform(*cfg.push_fraction) * (end.position - behind.position)
        return [approach, behind, replace(end, position=stop), replace(end, position=stop + [0, 0, 0.1])]
    raise ValueError(f"No failure for task family {family!r}")


class WaypointFollower:
    """Turns a waypoint list into `pd_ee_delta_pose` actions, one control step at a time.

    Args:
        waypoints: the plan.
        max_step: largest TCP translation per step (m); smaller gives slower, smoother motion.
        timeout: steps after which an unreached waypoint is skipped.
    """

    def __init__(
        self, waypoints: list[Waypoint], start_quat_wxyz: np.ndarray, max_step: float = 0.035, timeout: int = 40
    ):
        self.waypoints = waypoints
        self.start_rotation = Rotation.from_quat(start_quat_wxyz, scalar_first=True)
        self.max_step = max_step
        self.timeout = timeout
        self.index = 0
        self.steps_on_waypoint = 0
        self.held = 0
        self.skipped = 0

    @property
    def done(self) -> bool:
        return self.index >= len(self.waypoints)

    def act(self, tcp_pos: np.ndarray, tcp_quat_wxyz: np.ndarray) -> np.ndarray:
        """Action for the current TCP pose (world frame); advances through the plan as waypoints are reached."""
        while not self.done:
            waypoint = self.waypoints[self.index]
            pos_error = waypoint.position - tcp_pos
            target_rotation = Rotation.from_rotvec(waypoint.rotation) * self.start_rotation
            rot_error = target_rotation * Rotation.from_quat(tcp_quat_wxyz, scalar_first=True).inv()
            reached = np.linalg.norm(pos_error) < waypoint.tolerance and rot_error.magnitude() < 0.08
            if reached and self.held >= waypoint.hold:
                self._advance()
                continue
            if self.steps_on_waypoint >= self.timeout:
                self.skipped += 1
                self._advance()
                continue
            self.steps_on_waypoint += 1
            if reached:
                self.held += 1
            return self._action(pos_error, rot_error, waypoint.gripper)
        return self._action(np.zeros(3), Rotation.identity(), self.waypoints[-1].gripper)

    def _advance(self):
        self.index += 1
        self.steps_on_waypoint = 0
        self.held = 0

    def _action(self, pos_error: np.ndarray, rot_error: Rotation, gripper: float) -> np.ndarray:
        # The robot base is not rotated, so world-frame deltas are root-frame deltas.
        distance = np.linalg.norm(pos_error)
        step = pos_error if distance <= self.max_step else pos_error * (self.max_step / distance)
        euler = np.clip(rot_error.as_euler("XYZ"), -abs(ROT_SCALE), abs(ROT_SCALE))
        action = np.concatenate([step / POS_SCALE, euler / ROT_SCALE, [gripper]])
        return np.clip(action, -1.0, 1.0).astype(np.float32)


def plan_episode(
    env: RoboscapeTabletopEnv,
    kind: str,
    rng: np.random.Generator,
    suboptimal: SuboptimalConfig | None = None,
    failure: FailureConfig | None = None,
) -> WaypointFollower:
    """A follower of a `kind` (one of KINDS) plan for the env's freshly reset episode."""
    if kind not in KINDS:
        raise ValueError(f"Unknown plan kind {kind!r}; expected one of {KINDS}")
    plan = essential_waypoints(env)
    if kind == "suboptimal":
        plan = make_suboptimal(plan, rng, suboptimal or SuboptimalConfig())
    elif kind == "failed":
        spec = env.scene_spec.object
        radius = float(np.hypot(*spec.size[:2])) if spec.shape in ("cube", "box") else spec.size[0]
        plan = make_failed(plan, rng, env.family, radius, failure or FailureConfig())
    max_step = 0.035 if kind == "optimal" else float(rng.uniform(0.02, 0.035))
    start_quat = env.agent.tcp_pose.q[0].cpu().numpy()
    return WaypointFollower(plan, start_quat, max_step=max_step)
