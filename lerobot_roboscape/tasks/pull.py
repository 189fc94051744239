from mani_skill.utils.registration import register_env

from lerobot_roboscape.tasks.push import PushEnv


@register_env("RoboscapePull-v1", max_episode_steps=100)
class PullEnv(PushEnv):
    """**Task Description:**
    Pull the scene's object back (towards the robot, -x) by `distance` metres along the table.

    **Randomizations:**
    - the object's xy position in the far half of the workspace and its yaw in [-pi/8, pi/8]
    - the container (a distractor here) on the other side of the table in y
    - the robot's joint positions (small noise around the rest pose)

    **Success Conditions:**
    - the object moved at least `distance - tolerance` towards the robot
    - it drifted at most `lateral_tolerance` sideways and is still on the table
    """

    family = "pull"
    direction = -1.0
    object_spawn_x = (0.0, 0.1)
