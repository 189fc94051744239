"""Planner demonstrations saved in ManiSkill's own trajectory format (.h5 + .json), through its RecordEpisode
wrapper: the same files ManiSkill's tools write, for users who keep their data that way."""

from pathlib import Path

from mani_skill.utils.wrappers.record import RecordEpisode

from lerobot_roboscape.demos.rollout import EpisodeJob, run_planned_episode
from lerobot_roboscape.tasks.make import make_task_env


def record_maniskill_trajectories(
    out_dir: str | Path,
    family: str,
    scene_id: str,
    episodes: int = 2,
    image_size: int = 64,
    seed: int = 0,
    name: str = "trajectory",
) -> Path:
    """Record `episodes` optimal planner episodes with RGB observations; return the .h5 path."""
    env = make_task_env(family, scene_id, image_size=image_size)
    env = RecordEpisode(
        env,
        str(out_dir),
        save_trajectory=True,
        trajectory_name=name,
        save_video=False,
        source_type="roboscape_planner",
        source_desc=f"{family} waypoint planner",
    )
    try:
        for k in range(episodes):
            run_planned_episode(env, EpisodeJob(family, scene_id, seed + k, "optimal", image_size))
    finally:
        env.close()  # writes the last episode and the .json
    return Path(out_dir) / f"{name}.h5"
