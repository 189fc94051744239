"""A run's tokenizer and the world models it has trained in one folder that travels (no Hub here; a machine's outputs
die with it), as `--world_models` takes them: the next machine's run trains none of them again, and needs only the
data its later stages read. A run stopped after its tokenizer carries that alone (a chain of 3-hour sessions).

    python scripts/experiments/carry_world_models.py --run outputs/bench --out carried/bench
    roboscape-demo --scale=bench --output_dir=outputs/bench --world_models=carried/bench  # on another machine
"""

import argparse
import json
from pathlib import Path

from lerobot_roboscape.pipeline.given import carry


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "--run",
        type=Path,
        required=True,
        help="a roboscape-demo output_dir: its tokenizer, its world models if trained",
    )
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    print(json.dumps({"bytes": carry(args.run, args.out)}, indent=1))


if __name__ == "__main__":
    main()
