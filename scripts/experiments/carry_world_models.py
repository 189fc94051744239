"""A run's tokenizer and world models in one folder that travels (no Hub here; a machine's outputs die with it), as
`--world_models` takes them: the next machine's run trains no model, and needs only the data its later stages read.

    python scripts/experiments/carry_world_models.py --run outputs/bench --out carried/bench
    roboscape-demo --scale=bench --output_dir=outputs/bench --world_models=carried/bench  # on another machine
"""

import argparse
import json
from pathlib import Path

from lerobot_roboscape.pipeline.given import carry


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", type=Path, required=True, help="a roboscape-demo output_dir with its world models")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    print(json.dumps({"bytes": carry(args.run, args.out)}, indent=1))


if __name__ == "__main__":
    main()
