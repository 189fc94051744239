"""`roboscape-ppo`: PPO for a LeRobot policy in the world model (`--env.type=roboscape_wm`) or in the simulator
(`--env.type=roboscape_maniskill`). Runs on CPU, one GPU, or `accelerate launch roboscape-ppo ...` on several.

    roboscape-ppo --policy_path=outputs/sft_mlp/checkpoints/last/pretrained_model --env.type=roboscape_wm \
        --env.dataset_repo_id=local/roboscape --env.dataset_root=outputs/datasets/roboscape \
        --env.tokenizer=... --env.action_world_model=... --env.text_world_model=... --output_dir=outputs/ppo_wm
    roboscape-ppo ... --resume=true       # continue a killed run from its last checkpoint
"""

import logging

import draccus

from lerobot_roboscape.cli import one_line_errors
from lerobot_roboscape.rl.configuration_ppo import PPOConfig
from lerobot_roboscape.rl.ppo import train_ppo


@one_line_errors("roboscape-ppo")
def main(argv: list[str] | None = None):
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    final = train_ppo(draccus.parse(PPOConfig, args=argv))
    print(f"PPO policy saved to {final.resolve()}")


if __name__ == "__main__":
    main()
