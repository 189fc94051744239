import torch
from mani_skill.utils.registration import register_env

from lerobot_roboscape.tasks.base import RoboscapeTabletopEnv


@register_env("RoboscapePickPlace-v1", max_episode_steps=160)
class PickPlaceEnv(RoboscapeTabletopEnv):
    """**Task Description:**
    Pick up the scene's object and place it in the scene's container (plate or bowl).

    **Randomizations:**
    - the object's xy position on one side of the table (y < 0 or y > 0) and its yaw in [-pi/8, pi/8]
    - the container's xy position on the other side, at least 0.14 m away in y
    - the robot's joint positions (small noise around the rest pose)

    **Success Conditions:**
    - the object's centre is within the container's radius (minus a margin) in xy
    - the object rests low in the container (not held above it) and is released
    """

    family = "pick_place"
    max_dense_reward = 5.0
    container_x = (-0.06, 0.08)
    # Success tolerances (metres): the object's centre this far inside the container's rim, and at most this far
    # above resting on the container's floor (halfway up its wall).
    rim_margin = 0.015
    height_tolerance = 0.012

    def _initialize_episode(self, env_idx: torch.Tensor, options: dict):
        with torch.device(self.device):
            b = len(env_idx)
            self._reset_robot(env_idx)
            obj_xy = self._spawn_object(b)
            container_xy = torch.stack(
                [self._uniform(b, *self.container_x), self._away_from(obj_xy, min_gap=0.16)], dim=1
            )
            self._place(self.container, container_xy, 0.0)

    def evaluate(self):
        spec = self.scene_spec
        offset = self.obj.pose.p - self.container.pose.p
        inside = torch.linalg.norm(offset[:, :2], axis=1) <= spec.container.radius - self.rim_margin
        low = offset[:, 2] <= spec.object.half_height + self.height_tolerance + 0.5 * spec.container.wall_height
        is_grasped = self.agent.is_grasping(self.obj)
        return {
            "success": inside & low & ~is_grasped,
            "is_obj_in_container": inside & low,
            "is_grasped": is_grasped,
        }

    def compute_dense_reward(self, obs, action: torch.Tensor, info: dict):
        above_container = self.container.pose.p.clone()
        above_container[:, 2] += self.scene_spec.object.half_height + 0.05
        return self.carry_reward(above_container, info, "is_obj_in_container")
