import torch
from mani_skill.utils.registration import register_env

from lerobot_roboscape.tasks.base import RoboscapeTabletopEnv


@register_env("RoboscapePush-v1", max_episode_steps=100)
class PushEnv(RoboscapeTabletopEnv):
    """**Task Description:**
    Push the scene's object forward (away from the robot, +x) by `distance` metres along the table.

    **Randomizations:**
    - the object's xy position in the near half of the workspace and its yaw in [-pi/8, pi/8]
    - the container (a distractor here) on the other side of the table in y
    - the robot's joint positions (small noise around the rest pose)

    **Success Conditions:**
    - the object moved at least `distance - tolerance` along the push direction
    - it drifted at most `lateral_tolerance` sideways and is still on the table
    """

    family = "push"
    direction = 1.0  # +1: away from the robot; -1: towards it (see PullEnv)
    distance = 0.1
    tolerance = 0.025
    lateral_tolerance = 0.05
    max_dense_reward = 3.0
    object_spawn_x = (-0.1, -0.02)

    def _load_scene(self, options: dict):
        super()._load_scene(options)
        self.start_xy = torch.zeros((self.num_envs, 2), device=self.device)  # where each episode's object began

    def _initialize_episode(self, env_idx: torch.Tensor, options: dict):
        with torch.device(self.device):
            b = len(env_idx)
            self._reset_robot(env_idx)
            obj_xy = self._spawn_object(b)
            container_xy = torch.stack([self._uniform(b, -0.05, 0.05), self._away_from(obj_xy, min_gap=0.18)], dim=1)
            self._place(self.container, container_xy, 0.0)
            self.start_xy[env_idx] = obj_xy

    @property
    def goal_xy(self) -> torch.Tensor:
        goal = self.start_xy.clone()
        goal[:, 0] += self.direction * self.distance
        return goal

    def evaluate(self):
        moved = self.obj.pose.p[:, :2] - self.start_xy
        along = moved[:, 0] * self.direction
        far_enough = along >= self.distance - self.tolerance
        on_line = moved[:, 1].abs() <= self.lateral_tolerance
        return {
            "success": far_enough & on_line & self.object_rests_on_table(),
            "progress": (along / self.distance).clamp(max=1.0),
            "is_grasped": self.agent.is_grasping(self.obj),
        }

    def compute_dense_reward(self, obs, action: torch.Tensor, info: dict):
        behind = self.obj.pose.p.clone()
        behind[:, 0] -= self.direction * (self.scene_spec.object.size[0] + 0.02)
        reward = self.reach_reward(behind)
        to_goal = torch.linalg.norm(self.goal_xy - self.obj.pose.p[:, :2], axis=1)
        reward = reward + 2 * (1 - torch.tanh(10 * to_goal))
        reward[info["success"]] = self.max_dense_reward
        return reward
