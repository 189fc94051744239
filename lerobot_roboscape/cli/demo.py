"""`roboscape-demo`: the whole pipeline built so far, on CPU, in minutes, on an embedded default.

Stages: collect planner demonstrations in the task suite -> record ManiSkill trajectory files and convert them.
Each stage prints where its results are.
"""

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import draccus

from lerobot_roboscape.cli.collect import CollectConfig, collect
from lerobot_roboscape.cli.convert import ConvertConfig, convert
from lerobot_roboscape.demos.record import record_maniskill_trajectories
from lerobot_roboscape.tasks import TASK_FAMILIES, select_scenes


@dataclass
class DemoConfig:
    """Args:
    output_dir: where every artifact goes (replaced if it holds an earlier demo run).
    families: task families to collect.
    scenes: number of IND scenes per family.
    episodes_per_scene: planner episodes per (family, scene).
    image_size: camera resolution.
    workers: ManiSkill worker processes.
    """

    output_dir: str = "outputs/demo"
    families: list[str] = field(default_factory=lambda: list(TASK_FAMILIES))
    scenes: int = 2
    episodes_per_scene: int = 1
    image_size: int = 64
    workers: int = 2


def _stage(name: str):
    print(f"\n=== {name} ===", flush=True)
    return time.time()


def run_demo(cfg: DemoConfig) -> dict[str, Path]:
    out = Path(cfg.output_dir).resolve()
    artifacts: dict[str, Path] = {}

    start = _stage("1/2 collect planner demonstrations (ManiSkill, both cameras)")
    demos = out / "datasets" / "roboscape_demos"
    ds = collect(CollectConfig(repo_id="local/roboscape_demos", root=str(demos), families=cfg.families,
                               max_scenes=cfg.scenes, episodes_per_scene=cfg.episodes_per_scene,
                               image_size=cfg.image_size, workers=cfg.workers, overwrite=True, keep_failed=True))
    print(f"{ds.meta.total_episodes} episodes, {ds.meta.total_frames} frames in {time.time() - start:.0f}s")
    artifacts["demonstrations (LeRobotDataset)"] = demos

    start = _stage("2/2 record a ManiSkill trajectory file and convert it")
    scene = select_scenes("ind")[0]
    h5 = record_maniskill_trajectories(out / "maniskill_trajectories", cfg.families[0], scene.id, episodes=1,
                                       image_size=cfg.image_size)
    converted = out / "datasets" / "maniskill_converted"
    ds = convert(ConvertConfig(h5=str(h5), root=str(converted), repo_id="local/maniskill_converted",
                               overwrite=True))
    print(f"{ds.meta.total_episodes} episodes, {ds.meta.total_frames} frames in {time.time() - start:.0f}s")
    artifacts["ManiSkill trajectory file"] = h5
    artifacts["converted dataset (LeRobotDataset)"] = converted

    print("\n=== results ===")
    for name, path in artifacts.items():
        print(f"{name:40s} {path}")
    return artifacts


def main(argv: list[str] | None = None):
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    run_demo(draccus.parse(DemoConfig, args=argv))


if __name__ == "__main__":
    main()
