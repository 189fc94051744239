"""`roboscape-train-reward`: train a baseline reward model (the paper's embedding- or proxy-based reward).

    roboscape-train-reward --reward.kind=embedding --dataset.repo_id=local/roboscape \
        --dataset.root=outputs/datasets/roboscape --tokenizer=outputs/tokenizer/pretrained_model \
        --action_world_model=outputs/wm_action/pretrained_model --output_dir=outputs/reward_embedding
    roboscape-train-reward --reward.kind=proxy ... --output_dir=outputs/reward_proxy
"""

import logging

import draccus

from lerobot_roboscape.cli import one_line_errors
from lerobot_roboscape.reward.train import TrainRewardConfig, train_reward_model
from lerobot_roboscape.training.checkpoints import FINAL


@one_line_errors("roboscape-train-reward")
def main(argv: list[str] | None = None):
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    cfg = draccus.parse(TrainRewardConfig, args=argv)
    train_reward_model(cfg)
    print(f"{cfg.reward.kind} reward model saved to {(cfg.output_dir / FINAL).resolve()}")


if __name__ == "__main__":
    main()
