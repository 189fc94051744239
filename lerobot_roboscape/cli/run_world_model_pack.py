"""PPO in the world model where its models are (a lent GPU): the runs `roboscape-experiment --world_model_runs=DIR`
packed into DIR/pack, run in the world models given, into a folder that is then brought back to DIR/runs
(scripts/experiments/device_world_models.sh claim runs it after training the models).

    python -m lerobot_roboscape.cli.run_world_model_pack --pack=DIR/pack --action=.../pretrained_model \
        --text=.../pretrained_model --members=[...] --output_dir=/tmp/runs --time_budget_s=120
"""

import json
import logging

import draccus

from lerobot_roboscape.cli import one_line_errors
from lerobot_roboscape.experiments.world_model_runs import RunPackConfig, run_pack


@one_line_errors("run_world_model_pack")
def main(argv: list[str] | None = None):
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    print(json.dumps(run_pack(draccus.parse(RunPackConfig, args=argv)), indent=1))


if __name__ == "__main__":
    main()
