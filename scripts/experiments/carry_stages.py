"""A run's completed stages (its data, models, reports, SFT and PPO runs) in one folder that travels, and taken into
the same run on the next machine, which then skips them: a chain of 3-hour sessions on machines whose outputs die
with them, where collecting the bench's data alone takes more than a session on a slow CPU.

    python scripts/experiments/carry_stages.py --run outputs/bench --out carried/bench72_run
    python scripts/experiments/carry_stages.py --run outputs/bench --take carried/bench72_run  # the next machine
"""

import argparse
import json
from pathlib import Path

from lerobot_roboscape.pipeline.carried_stages import carry_stages, take_stages


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", type=Path, required=True, help="a roboscape-demo output_dir")
    group = parser.add_mutually_exclusive_group(required=True)
    group.add_argument("--out", type=Path, help="write the run's completed stages here")
    group.add_argument("--take", type=Path, help="take the stages carried here into the run")
    args = parser.parse_args()
    if args.out:
        print(json.dumps({"bytes": carry_stages(args.run, args.out)}, indent=1))
    else:
        print(json.dumps({"taken": take_stages(args.take, args.run)}, indent=1))


if __name__ == "__main__":
    main()
