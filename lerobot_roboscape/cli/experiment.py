"""`roboscape-experiment`: the paper's claim (Table 1) on the models a `roboscape-demo` run trained: PPO from the
SFT checkpoint in `roboscape_wm`, in `roboscape_maniskill` in one scene and in every training scene at equal
wall-clock (and the reward ablation), success in the simulator IND and OOD with 95% intervals of the differences,
the simulator success of PPO's checkpoints along its run, world-model rollouts replayed in the simulator, and the
report (lerobot_roboscape/experiments/experiment.py). A rerun skips the steps already complete.

    roboscape-experiment --pipeline.scale=bench --pipeline.output_dir=outputs/bench --report_dir=docs/results/bench
    roboscape-experiment ... --sft_checkpoint=path/to/pretrained_model   # start PPO from a policy you have
"""

import logging
import sys

from lerobot_roboscape.cli import one_line_errors
from lerobot_roboscape.experiments.experiment import ExperimentConfig, Packed, run_or_pack
from lerobot_roboscape.pipeline.config import parse_config


@one_line_errors("roboscape-experiment")
def main(argv: list[str] | None = None):
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    result = run_or_pack(parse_config(ExperimentConfig, sys.argv[1:] if argv is None else argv, "pipeline."))
    if not isinstance(result, Packed):  # the pack has said what to do next
        print(f"report: {result}")


if __name__ == "__main__":
    main()
