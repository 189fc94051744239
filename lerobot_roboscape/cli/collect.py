"""`roboscape-collect`: planner demonstrations in the task suite, written as a LeRobotDataset v3.

    roboscape-collect --families='[pick_place,push]' --split=ind --episodes_per_scene=4 \
        --failed_fraction=0.25 --suboptimal_fraction=0.5 --root=outputs/datasets/demos
    roboscape-collect ... --resume=true     # continue a killed collection from the episodes it saved
"""

import logging
from pathlib import Path

import draccus

from lerobot_roboscape.cli import one_line_errors
from lerobot_roboscape.demos.collect import CollectConfig, collect
from lerobot_roboscape.tasks import SCENES


@one_line_errors("roboscape-collect")
def main(argv: list[str] | None = None):
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    cfg = draccus.parse(CollectConfig, args=argv)
    if cfg.list_scenes:
        for scene in SCENES:
            print(f"{scene.id:40s} {scene.split}")
        return
    meta = collect(cfg).meta
    print(f"Wrote {meta.total_episodes} episodes, {meta.total_frames} frames to {Path(cfg.root).resolve()}")


if __name__ == "__main__":
    main()
