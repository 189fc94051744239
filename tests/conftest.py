import gymnasium as gym
import numpy as np
import pytest

from lerobot_roboscape.cli.collect import CollectConfig, collect

IMAGE_SIZE = 32


@pytest.fixture(scope="session")
def demo_dataset(tmp_path_factory):
    """A small real collection: two families, two scenes, one optimal and one suboptimal episode each."""
    root = tmp_path_factory.mktemp("collect") / "demos"
    cfg = CollectConfig(repo_id="test/demos", root=str(root), families=["pick_place", "push"], max_scenes=1,
                        episodes_per_scene=2, suboptimal_fraction=0.5, image_size=IMAGE_SIZE, workers=2,
                        keep_failed=True, seed=3)
    return collect(cfg), root


def record_maniskill_file(out_dir, obs_mode="rgb", episodes=2, steps=6, env_id="PickCube-v1") -> "Path":
    """Trajectory file written by ManiSkill's own RecordEpisode wrapper (random actions)."""
    import mani_skill.envs  # noqa: F401  registers PickCube-v1
    from mani_skill.utils.wrappers.record import RecordEpisode

    env = gym.make(env_id, obs_mode=obs_mode, control_mode="pd_ee_delta_pose", max_episode_steps=steps,
                   sensor_configs=dict(width=IMAGE_SIZE, height=IMAGE_SIZE))
    env = RecordEpisode(env, str(out_dir), save_trajectory=True, trajectory_name="traj", save_video=False,
                        source_type="test", source_desc="random actions")
    rng = np.random.default_rng(0)
    for k in range(episodes):
        env.reset(seed=k)
        for _ in range(steps + k):  # episodes of different lengths; the time limit ends each at `steps`
            _, _, terminated, truncated, _ = env.step(rng.uniform(-1, 1, 7).astype(np.float32))
            if bool(terminated.any()) or bool(truncated.any()):
                break
    env.close()
    return out_dir / "traj.h5"
