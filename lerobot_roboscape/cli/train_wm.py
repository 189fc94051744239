"""`roboscape-train-wm`: train the action or the text world model (Accelerate: CPU, one GPU or `accelerate launch`).

    roboscape-train-wm --dataset.repo_id=local/roboscape --dataset.root=outputs/datasets/roboscape \
        --tokenizer=outputs/tokenizer/pretrained_model --wm.control=action --output_dir=outputs/wm_action
    roboscape-train-wm ... --wm.control=text --output_dir=outputs/wm_text
    # the action model also on exploratory episodes, its retrieval and action gain read on a controllability set
    roboscape-train-wm ... --exploration.repo_id=local/roboscape_explore --exploration.root=outputs/datasets/explore \
        --exploration_share=0.5 --heldout_control.root=outputs/datasets/roboscape_controllability --train.eval_freq=150
    roboscape-train-wm ... --train.resume=true      # continue a killed run from its last checkpoint
"""

import logging

import draccus

from lerobot_roboscape.cli import one_line_errors
from lerobot_roboscape.training.checkpoints import FINAL
from lerobot_roboscape.world_model.train import TrainWorldModelConfig, train_world_model


@one_line_errors("roboscape-train-wm")
def main(argv: list[str] | None = None):
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    cfg = draccus.parse(TrainWorldModelConfig, args=argv)
    train_world_model(cfg)
    print(f"World model ({cfg.wm.control}) saved to {(cfg.output_dir / FINAL).resolve()}")


if __name__ == "__main__":
    main()
