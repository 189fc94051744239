"""`roboscape-convert`: official ManiSkill trajectory files (.h5 + .json) to a LeRobotDataset v3, written
atomically (a killed or refused conversion leaves no dataset behind).

    roboscape-convert --h5=demos/PickCube-v1/motionplanning/trajectory.rgb.pd_ee_delta_pose.physx_cpu.h5 \
        --task="pick up the cube" --root=outputs/datasets/pickcube
"""

import logging
from pathlib import Path

import draccus

from lerobot_roboscape.cli import one_line_errors
from lerobot_roboscape.dataset.convert import ConvertConfig, convert


@one_line_errors("roboscape-convert")
def main(argv: list[str] | None = None):
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    cfg = draccus.parse(ConvertConfig, args=argv)
    meta = convert(cfg).meta
    print(f"Wrote {meta.total_episodes} episodes, {meta.total_frames} frames to {Path(cfg.root).resolve()}")


if __name__ == "__main__":
    main()
