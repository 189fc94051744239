"""`roboscape-demo`: the whole RoboScape-R pipeline on an embedded default, one stage after another.

Stages (lerobot_roboscape/pipeline/stages.py): collect planner demonstrations in the task suite, held-out episodes
in OOD scenes, and a recorded ManiSkill trajectory file converted to a LeRobotDataset -> train the image tokenizer
-> train the action and the text world models -> the world model's fidelity report -> the baseline reward models
and the reward report -> random actions in `roboscape_wm` -> SFT with `lerobot-train` -> `lerobot-eval` in
`roboscape_wm` -> PPO in `roboscape_wm` and in `roboscape_maniskill` -> success in the simulator, IND and OOD
(Table 1) -> a push of every artifact with its card (to a local folder shaped like the Hub repos, or to the Hub with
`--push_to_hub=true`) -> the experiment's report. A rerun skips the stages already complete in --output_dir.

    roboscape-demo                      # tiny presets, CPU, minutes on 2 cores
    roboscape-demo --scale=smoke        # the smallest run of every stage (the end-to-end test)
    roboscape-demo --scale=bench --output_dir=outputs/bench --report_dir=docs/results/bench   # hours on 2 cores
    roboscape-demo --scale=bench --wm_train.steps=6000    # any setting of a scale, by its stage's own name
    roboscape-demo --scale=bench_gpu --output_dir=outputs/bench   # bench with the models trained on one GPU
    roboscape-demo --scale=paper --push_to_hub=true --hub_namespace=me   # paper presets, GPUs
"""

import logging
import sys

from lerobot_roboscape.cli import one_line_errors
from lerobot_roboscape.pipeline.config import PipelineConfig, parse_config
from lerobot_roboscape.pipeline.run import run_pipeline


@one_line_errors("roboscape-demo")
def main(argv: list[str] | None = None):
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    run_pipeline(parse_config(PipelineConfig, sys.argv[1:] if argv is None else argv))


if __name__ == "__main__":
    main()
