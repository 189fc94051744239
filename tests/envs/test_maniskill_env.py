import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from lerobot_roboscape.envs.batched import SingleEnv
from lerobot_roboscape.envs.configs import RoboscapeManiSkillEnvConfig, RoboscapeWorldModelEnvConfig
from lerobot_roboscape.envs.maniskill_env import RoboscapeManiSkillEnv
from lerobot_roboscape.tasks import get_scene
from tests.conftest import IMAGE_SIZE

pytestmark = pytest.mark.slow  # the simulator, or commands in subprocesses


def make_config(**overrides):
    # One process: spreading the envs over workers is tested in test_simulator_slots.py.
    return RoboscapeManiSkillEnvConfig(**{"image_size": IMAGE_SIZE, "episode_length": 4, "workers": 1, **overrides})


def test_gymnasium_env_checker():
    check_env(SingleEnv(RoboscapeManiSkillEnv(make_config(families=["push"]), num_envs=1)), skip_render_check=False)


def test_same_layout_as_the_world_model_env():
    ms, wm = make_config(), RoboscapeWorldModelEnvConfig(image_size=IMAGE_SIZE)
    assert ms.features == wm.features and ms.features_map == wm.features_map


def test_batched_episodes_over_families_and_scenes():
    scene = "red_cube-plate-wooden"
    env = RoboscapeManiSkillEnv(make_config(families=["pick_place", "push"]), num_envs=2)
    obs, info = env.reset(seed=0, options={"scene_id": scene})
    assert info["task"] == [get_scene(scene).instruction("pick_place"), get_scene(scene).instruction("push")]
    assert obs["pixels"]["third_view"].shape == (2, IMAGE_SIZE, IMAGE_SIZE, 3) and obs in env.observation_space
    for _ in range(4):
        obs, reward, terminated, truncated, info = env.step(np.zeros((2, 7), np.float32))
    assert (terminated | truncated).all() and not info["is_success"].any()  # holding still solves nothing
    assert env.call("task") == tuple(info_task for info_task in env.tasks())
    with pytest.raises(ValueError, match="NaN or inf"):
        env.step(np.full((2, 7), np.nan, np.float32))


def test_ood_split_only_draws_ood_scenes():
    env = RoboscapeManiSkillEnv(make_config(families=["push"], split="ood"), num_envs=1)
    assert {s.split for s in env.scenes} == {"ood"}
    _, info = env.reset(seed=1)
    assert get_scene(str(info["scene_id"][0])).split == "ood"


def test_fixed_horizons_per_family(demo_dataset):
    from lerobot_roboscape.dataset.reader import episode_facts, open_dataset

    # No dataset: each task's registered time limit.
    env = RoboscapeManiSkillEnv(make_config(families=["pick_place", "push"], episode_length=None), num_envs=2)
    assert env.horizons.tolist() == [160, 100] and env.call("_max_episode_steps")[0] == 160
    # A dataset: each family's longest successful demonstration.
    _, root = demo_dataset
    data = open_dataset("test/demos", root)
    longest = {}
    for i in range(data.meta.total_episodes):
        facts = episode_facts(data, i)
        if facts["success"]:
            longest[facts["task_family"]] = max(longest.get(facts["task_family"], 0), data.meta.episodes[i]["length"])
    env = RoboscapeManiSkillEnv(
        make_config(
            families=["pick_place", "push"], episode_length=None, dataset_repo_id="test/demos", dataset_root=str(root)
        ),
        num_envs=2,
    )
    assert env.horizons.tolist() == [longest["pick_place"], longest["push"]]
