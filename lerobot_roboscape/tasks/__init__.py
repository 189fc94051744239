"""The ManiSkill task suite of RoboScape-R: four task families over the scenes of `scenes.py`.

Importing this package registers the ManiSkill env ids in `ENV_IDS`.
"""

from mani_skill.utils.registration import REGISTERED_ENVS

from lerobot_roboscape.tasks.base import RoboscapeTabletopEnv
from lerobot_roboscape.tasks.move_to_aim import MoveToAimEnv
from lerobot_roboscape.tasks.pick_place import PickPlaceEnv
from lerobot_roboscape.tasks.pull import PullEnv
from lerobot_roboscape.tasks.push import PushEnv
from lerobot_roboscape.tasks.scenes import SCENES, TASK_FAMILIES, Scene, get_scene, select_scenes

# Task family -> ManiSkill env id, from the task classes registered above (a new family needs only its class).
ENV_IDS: dict[str, str] = {
    spec.cls.family: env_id
    for env_id, spec in REGISTERED_ENVS.items()
    if issubclass(spec.cls, RoboscapeTabletopEnv) and spec.cls.family
}

__all__ = [
    "ENV_IDS",
    "SCENES",
    "TASK_FAMILIES",
    "Scene",
    "get_scene",
    "select_scenes",
    "PickPlaceEnv",
    "PushEnv",
    "PullEnv",
    "MoveToAimEnv",
]
