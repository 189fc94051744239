import sapien
import torch
from mani_skill.utils.building import actors
from mani_skill.utils.registration import register_env

from lerobot_roboscape.tasks.base import RoboscapeTabletopEnv


@register_env("RoboscapeMoveToAim-v1", max_episode_steps=160)
class MoveToAimEnv(RoboscapeTabletopEnv):
    """**Task Description:**
    Move the scene's object onto the target carpet (a flat red-and-white disc lying on the table).

    **Randomizations:**
    - the object's xy position and its yaw in [-pi/8, pi/8]
    - the carpet's xy position on the other side of the table in y, at least 0.14 m away
    - the container (a distractor here) at the far edge of the workspace
    - the robot's joint positions (small noise around the rest pose)

    **Success Conditions:**
    - the object's centre lies over the carpet (within its radius minus a margin)
    - the object rests on the table and is released
    """

    family = "move_to_aim"
    carpet_radius = 0.06
    carpet_margin = 0.01  # success tolerance (metres): the object's centre this far inside the carpet's edge
    max_dense_reward = 5.0

    def _load_task_extras(self):
        self.carpet = actors.build_red_white_target(
            self.scene,
            radius=self.carpet_radius,
            thickness=0.002,
            name="carpet",
            body_type="kinematic",
            add_collision=False,
            initial_pose=sapien.Pose(p=[0, -0.2, 0.001]),
        )

    def _initialize_episode(self, env_idx: torch.Tensor, options: dict):
        with torch.device(self.device):
            b = len(env_idx)
            self._reset_robot(env_idx)
            obj_xy = self._spawn_object(b, y_range=(-0.12, 0.12))
            carpet_xy = torch.stack([self._uniform(b, -0.06, 0.08), self._away_from(obj_xy, min_gap=0.15)], dim=1)
            self._place(self.carpet, carpet_xy, 0.001)
            container_xy = torch.stack([torch.full((b,), 0.2), -carpet_xy[:, 1].sign() * 0.22], dim=1)
            self._place(self.container, container_xy, 0.0)

    def evaluate(self):
        offset = self.obj.pose.p[:, :2] - self.carpet.pose.p[:, :2]
        on_carpet = torch.linalg.norm(offset, axis=1) <= self.carpet_radius - self.carpet_margin
        is_grasped = self.agent.is_grasping(self.obj)
        on_table = self.object_rests_on_table()
        return {
            "success": on_carpet & on_table & ~is_grasped,
            "is_obj_on_carpet": on_carpet & on_table,
            "is_grasped": is_grasped,
        }

    def compute_dense_reward(self, obs, action: torch.Tensor, info: dict):
        above_carpet = self.carpet.pose.p.clone()
        above_carpet[:, 2] = self.scene_spec.object.half_height + 0.03
        return self.carry_reward(above_carpet, info, "is_obj_on_carpet")
