import gymnasium as gym
import torch

from lerobot_roboscape.tasks import ENV_IDS, TASK_FAMILIES
from roboscape_core.errors import InvalidInputError

CONTROL_MODE = "pd_ee_delta_pose"  # 7-D: xyz delta, rotation delta (XYZ Euler), gripper; all in [-1, 1]


def make_task_env(family: str, scene_id: str, image_size: int = 64, obs_mode: str = "rgb", **kwargs) -> gym.Env:
    """One ManiSkill env of a task family in one scene, with both cameras at `image_size` pixels square. It renders
    on the CPU where no CUDA device is visible: asked for the GPU there, ManiSkill falls back to the CPU anyway and
    warns once per env."""
    if family not in ENV_IDS:
        raise InvalidInputError(f"Unknown task family {family!r}; expected one of {TASK_FAMILIES}")
    return gym.make(
        ENV_IDS[family],
        scene_id=scene_id,
        obs_mode=obs_mode,
        control_mode=CONTROL_MODE,
        robot_uids="panda_wristcam",
        sensor_configs=dict(width=image_size, height=image_size),
        **{"render_backend": "gpu" if torch.cuda.is_available() else "cpu"} | kwargs,
    )
