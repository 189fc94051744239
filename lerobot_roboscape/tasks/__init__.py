"""The ManiSkill task suite of RoboScape-R: four task families over the scenes of `scenes.py`.

Importing this package registers the ManiSkill env ids in `ENV_IDS`.
"""

from lerobot_roboscape.tasks.move_to_aim import MoveToAimEnv
from lerobot_roboscape.tasks.pick_place import PickPlaceEnv
from lerobot_roboscape.tasks.pull import PullEnv
from lerobot_roboscape.tasks.push import PushEnv
from lerobot_roboscape.tasks.scenes import SCENES, TASK_FAMILIES, Scene, get_scene, select_scenes

ENV_IDS: dict[str, str] = {
    "pick_place": "RoboscapePickPlace-v1",
    "push": "RoboscapePush-v1",
    "pull": "RoboscapePull-v1",
    "move_to_aim": "RoboscapeMoveToAim-v1",
}

__all__ = [
    "ENV_IDS", "SCENES", "TASK_FAMILIES", "Scene", "get_scene", "select_scenes",
    "PickPlaceEnv", "PushEnv", "PullEnv", "MoveToAimEnv",
]
