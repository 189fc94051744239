import numpy as np
import pytest

from lerobot_roboscape.demos.rollout import EpisodeJob, run_planned_episode
from lerobot_roboscape.tasks import TASK_FAMILIES
from lerobot_roboscape.tasks.make import make_task_env

pytestmark = pytest.mark.slow  # the simulator, or commands in subprocesses

SCENE = "green_cube-plate-grey"


@pytest.mark.parametrize("family", TASK_FAMILIES)
def test_optimal_plan_succeeds_and_reward_peaks_at_success(family):
    env = make_task_env(family, SCENE, image_size=32)
    try:
        obs, _ = env.reset(seed=5)
        assert {k: tuple(v["rgb"].shape) for k, v in obs["sensor_data"].items()} == {
            "third_view": (1, 32, 32, 3),
            "hand_camera": (1, 32, 32, 3),
        }
        assert env.action_space.shape == (7,)
        episode = run_planned_episode(env, EpisodeJob(family, SCENE, seed=5, kind="optimal", image_size=32))
    finally:
        env.close()
    assert episode.succeeded, f"{family}: the optimal plan should solve {SCENE}"
    assert not episode.success[0]
    assert episode.reward[-1] > episode.reward[0]
    assert np.abs(episode.action).max() <= 1.0
    assert set(episode.images) == {"third_view", "wrist"}
    assert episode.info["split"] == "ind" and episode.info["task_family"] == family


def test_reset_switches_scene_and_seed_is_deterministic():
    env = make_task_env("push", SCENE, image_size=32)
    try:
        first = env.reset(seed=1)[0]["extra"]["tcp_pose"].clone()
        env.reset(seed=2, options={"scene_id": "orange_ball-bowl-wooden"})
        assert env.unwrapped.scene_spec.object.name == "orange ball"
        assert env.unwrapped.instruction == "push the orange ball forward"
        env.reset(seed=1, options={"scene_id": SCENE})
        again = env.unwrapped.agent.tcp_pose.raw_pose
        assert np.allclose(first.numpy(), again.numpy(), atol=1e-4)
    finally:
        env.close()
