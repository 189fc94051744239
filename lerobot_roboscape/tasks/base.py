"""Shared tabletop for the four task families: robot, two cameras, table, object and container of one scene.

Each family (one file each, ManiSkill style) subclasses `RoboscapeTabletopEnv` and adds its episode layout,
success evaluation and dense reward.
"""

from typing import Any

import numpy as np
import sapien
import torch
from mani_skill.agents.robots.panda.panda_wristcam import PandaWristCam
from mani_skill.envs.sapien_env import BaseEnv
from mani_skill.sensors.camera import CameraConfig
from mani_skill.utils import sapien_utils
from mani_skill.utils.building.ground import build_ground
from mani_skill.utils.scene_builder.table import TableSceneBuilder
from mani_skill.utils.structs.actor import Actor
from mani_skill.utils.structs.pose import Pose
from transforms3d.euler import euler2quat

from lerobot_roboscape.tasks.scenes import SCENES, ContainerSpec, ObjectSpec, TableSpec, get_scene
from lerobot_roboscape.tasks.wrist_camera_mesh import lighten_wrist_camera

ROBOT_BASE_XYZ = (-0.615, 0.0, 0.0)
# Panda rest pose with the gripper pointing down; the wrist camera variant is rotated by -pi/4 on joint 7.
PANDA_REST_QPOS = np.array([0.0, np.pi / 8, 0, -np.pi * 5 / 8, 0, np.pi * 3 / 4, -np.pi / 4, 0.04, 0.04])
BOX_TABLE_HALF_SIZE = (0.6, 0.8, 0.45)


def build_table(env: BaseEnv, spec: TableSpec) -> None:
    """Table top at z=0 with a ground plane under it."""
    if spec.style == "maniskill_wood":
        TableSceneBuilder(env).build()
        return
    hx, hy, hz = BOX_TABLE_HALF_SIZE
    builder = env.scene.create_actor_builder()
    builder.add_box_collision(half_size=[hx, hy, hz])
    builder.add_box_visual(half_size=[hx, hy, hz], material=sapien.render.RenderMaterial(base_color=spec.color))
    builder.initial_pose = sapien.Pose(p=[-0.12, 0, -hz])
    builder.build_kinematic(name="table-workspace")
    build_ground(env.scene, altitude=-2 * hz)


def build_object(env: BaseEnv, spec: ObjectSpec) -> Actor:
    builder = env.scene.create_actor_builder()
    material = sapien.render.RenderMaterial(base_color=spec.color)
    if spec.shape in ("cube", "box"):
        builder.add_box_collision(half_size=spec.size)
        builder.add_box_visual(half_size=spec.size, material=material)
    elif spec.shape == "sphere":
        builder.add_sphere_collision(radius=spec.size[0])
        builder.add_sphere_visual(radius=spec.size[0], material=material)
    elif spec.shape == "cylinder":
        # SAPIEN cylinders lie along x; stand them up.
        upright = sapien.Pose(q=euler2quat(0, np.pi / 2, 0))
        builder.add_cylinder_collision(radius=spec.size[0], half_length=spec.size[1], pose=upright)
        builder.add_cylinder_visual(radius=spec.size[0], half_length=spec.size[1], pose=upright, material=material)
    else:
        raise ValueError(f"Object {spec.name!r} has unknown shape {spec.shape!r}")
    builder.initial_pose = sapien.Pose(p=[0, 0, spec.half_height])
    return builder.build(name="object")


def build_container(env: BaseEnv, spec: ContainerSpec, wall_segments: int = 12) -> Actor:
    """A flat disc (plate), with a ring of wall segments when it is a bowl. Kinematic: it never moves."""
    builder = env.scene.create_actor_builder()
    material = sapien.render.RenderMaterial(base_color=spec.color)
    base_half = 0.004
    base_pose = sapien.Pose(p=[0, 0, base_half], q=euler2quat(0, np.pi / 2, 0))
    builder.add_cylinder_collision(radius=spec.radius, half_length=base_half, pose=base_pose)
    builder.add_cylinder_visual(radius=spec.radius, half_length=base_half, pose=base_pose, material=material)
    if spec.wall_height > 0:
        wall_half = [0.004, np.pi * spec.radius / wall_segments, spec.wall_height / 2]
        for k in range(wall_segments):
            angle = 2 * np.pi * k / wall_segments
            pose = sapien.Pose(
                p=[spec.radius * np.cos(angle), spec.radius * np.sin(angle), spec.wall_height / 2],
                q=euler2quat(0, 0, angle),
            )
            builder.add_box_collision(half_size=wall_half, pose=pose)
            builder.add_box_visual(half_size=wall_half, pose=pose, material=material)
    builder.initial_pose = sapien.Pose(p=[0, 0.2, 0])
    return builder.build_kinematic(name="container")


class RoboscapeTabletopEnv(BaseEnv):
    """Panda with a wrist camera at a table holding one object and one container (the scene).

    Subclasses set `family` and implement `_initialize_episode`, `evaluate` and `compute_dense_reward`.
    The scene is chosen by `scene_id` at construction, or changed later with
    `reset(options={"scene_id": ...})`. Every reset rebuilds the scene. `light_wrist_camera` (default) renders the
    wrist camera's body with a light mesh (tasks/wrist_camera_mesh.py: 3.5x faster software rendering); False
    renders ManiSkill's own.
    """

    SUPPORTED_ROBOTS = ["panda_wristcam"]
    SUPPORTED_REWARD_MODES = ["normalized_dense", "dense", "sparse", "none"]
    agent: PandaWristCam
    family: str = ""
    max_dense_reward: float = 1.0

    # Success tolerance (metres): an object whose centre is this close to its resting height is on the table.
    rest_height_tolerance = 0.01

    # Layout of the workspace (metres, world frame; the robot base is at x=-0.615 facing +x).
    object_spawn_x = (-0.08, 0.06)
    object_spawn_y = (-0.14, 0.14)

    def __init__(
        self,
        *args,
        scene_id: str = SCENES[0].id,
        robot_uids="panda_wristcam",
        robot_init_qpos_noise=0.02,
        light_wrist_camera: bool = True,
        **kwargs,
    ):
        self.scene_spec = get_scene(scene_id)
        self.robot_init_qpos_noise = robot_init_qpos_noise
        self.light_wrist_camera = light_wrist_camera
        super().__init__(*args, robot_uids=robot_uids, **kwargs)

    @property
    def instruction(self) -> str:
        return self.scene_spec.instruction(self.family)

    def reset(self, seed=None, options=None):
        options = dict(options or {})
        scene_id = options.pop("scene_id", None)
        if scene_id is not None:
            self.scene_spec = get_scene(scene_id)
        # Every reset rebuilds the scene (0.3 s on CPU): PhysX keeps contact state across a plain reset, so an
        # episode would depend, to the last bits, on the episodes before it in the same env, and a resumed
        # collection or PPO run could not equal an uninterrupted one.
        options["reconfigure"] = True
        return super().reset(seed=seed, options=options)

    # Cameras.
    @property
    def _default_sensor_configs(self):
        # Framed on the workspace (objects spawn within x in [-0.1, 0.06], |y| <= 0.14, pushed up to x = 0.08) so
        # that a 4 cm object covers about 7 px of a 64 px image; a wider view left it 3-4 px, which the
        # tokenizer's 16x16 grid could not keep.
        pose = sapien_utils.look_at(eye=[0.22, 0.0, 0.38], target=[-0.06, 0.0, 0.0])
        return [CameraConfig("third_view", pose, 128, 128, 0.8, 0.01, 100)]

    @property
    def _default_human_render_camera_configs(self):
        pose = sapien_utils.look_at(eye=[0.6, 0.6, 0.6], target=[-0.1, 0.0, 0.1])
        return CameraConfig("render_camera", pose, 512, 512, 1, 0.01, 100)

    # Scene.
    def _load_agent(self, options: dict):
        super()._load_agent(options, sapien.Pose(p=list(ROBOT_BASE_XYZ)))
        if self.light_wrist_camera:
            lighten_wrist_camera(self.agent)

    def _load_scene(self, options: dict):
        build_table(self, self.scene_spec.table)
        self.container = build_container(self, self.scene_spec.container)
        self.obj = build_object(self, self.scene_spec.object)
        self._load_task_extras()

    def _load_task_extras(self):
        """Family-specific actors (e.g. the target carpet)."""

    # Episode helpers.
    def _reset_robot(self, env_idx: torch.Tensor):
        b = len(env_idx)
        qpos = PANDA_REST_QPOS + self._episode_rng.normal(0, self.robot_init_qpos_noise, (b, len(PANDA_REST_QPOS)))
        qpos[:, -2:] = 0.04
        self.agent.reset(qpos)
        self.agent.robot.set_pose(sapien.Pose(p=list(ROBOT_BASE_XYZ)))

    def _uniform(self, b: int, low: float, high: float) -> torch.Tensor:
        return torch.rand(b) * (high - low) + low

    def _place(self, actor: Actor, xy: torch.Tensor, z: float, yaw: torch.Tensor | None = None):
        xyz = torch.zeros((len(xy), 3))
        xyz[:, :2] = xy
        xyz[:, 2] = z
        if yaw is None:
            actor.set_pose(Pose.create_from_pq(p=xyz))
            return
        q = torch.zeros((len(xy), 4))
        q[:, 0] = torch.cos(yaw / 2)
        q[:, 3] = torch.sin(yaw / 2)
        actor.set_pose(Pose.create_from_pq(p=xyz, q=q))

    def _spawn_object(self, b: int, x_range=None, y_range=None) -> torch.Tensor:
        x = self._uniform(b, *(x_range or self.object_spawn_x))
        y = self._uniform(b, *(y_range or self.object_spawn_y))
        xy = torch.stack([x, y], dim=1)
        yaw = self._uniform(b, -np.pi / 8, np.pi / 8)
        self._place(self.obj, xy, self.scene_spec.object.half_height, yaw)
        return xy

    def _away_from(self, xy: torch.Tensor, min_gap: float, y_extent: float = 0.18) -> torch.Tensor:
        """A y coordinate on the other side of the table from `xy`, at least `min_gap` away."""
        side = torch.where(xy[:, 1] > 0, -1.0, 1.0)
        offset = self._uniform(len(xy), min_gap, min_gap + 0.06)
        return (xy[:, 1] + side * offset).clamp(-y_extent, y_extent)

    # Shared observation and evaluation pieces.
    def _get_obs_extra(self, info: dict):
        return dict(tcp_pose=self.agent.tcp_pose.raw_pose, is_grasped=info["is_grasped"])

    def object_rests_on_table(self) -> torch.Tensor:
        return self.obj.pose.p[:, 2] < self.scene_spec.object.half_height + self.rest_height_tolerance

    def reach_reward(self, target_xyz: torch.Tensor) -> torch.Tensor:
        return 1 - torch.tanh(5 * torch.linalg.norm(target_xyz - self.agent.tcp_pose.p, axis=1))

    def carry_reward(self, target_xyz: torch.Tensor, info: dict, placed_key: str) -> torch.Tensor:
        """Staged reward for carrying the object to `target_xyz`: reach, grasp, approach, placed; max at success."""
        is_grasped = info["is_grasped"].float()
        to_target = torch.linalg.norm(target_xyz - self.obj.pose.p, axis=1)
        reward = self.reach_reward(self.obj.pose.p) + is_grasped + (1 - torch.tanh(5 * to_target)) * is_grasped
        reward = reward + 2 * info[placed_key].float()
        reward[info["success"]] = self.max_dense_reward
        return reward

    def compute_normalized_dense_reward(self, obs: Any, action: torch.Tensor, info: dict):
        return self.compute_dense_reward(obs=obs, action=action, info=info) / self.max_dense_reward
