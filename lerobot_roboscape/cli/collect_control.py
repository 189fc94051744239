"""`roboscape-collect-control`: the controllability set, K action sequences replayed from each held-out start.

    roboscape-collect-control --split=ood --max_scenes=8 --starts_per_scene=2 --sequences=4 \
        --root=outputs/datasets/roboscape_controllability
"""

import logging
from pathlib import Path

import draccus

from lerobot_roboscape.cli import one_line_errors
from lerobot_roboscape.demos.controllability import ControllabilityConfig, collect_controllability


@one_line_errors("roboscape-collect-control")
def main(argv: list[str] | None = None):
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    cfg = draccus.parse(ControllabilityConfig, args=argv)
    meta = collect_controllability(cfg).meta
    print(f"Wrote {meta.total_episodes} episodes, {meta.total_frames} frames to {Path(cfg.root).resolve()}")


if __name__ == "__main__":
    main()
