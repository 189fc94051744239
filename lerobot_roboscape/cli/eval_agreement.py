"""`roboscape-eval-agreement`: the same policies from the same initial states in the simulator and in the world
model; per-episode outcomes side by side, the confusion table and the ladder's ranking.

roboscape-eval-agreement --policy_paths='[outputs/sft/checkpoints/002000/pretrained_model,outputs/ppo/last]' \
    --env.dataset_repo_id=local/roboscape_demos --env.dataset_root=outputs/demos \
    --env.tokenizer=outputs/tokenizer/pretrained_model \
    --env.action_world_model=outputs/world_model_action/pretrained_model \
    --env.text_world_model=outputs/world_model_text/pretrained_model \
    --env.similarity=tokenizer --families='[push]' --split=ood --episodes=50 --output_dir=outputs/agreement
"""

import logging

import draccus

from lerobot_roboscape.cli import one_line_errors
from lerobot_roboscape.evaluation.agreement import AgreementConfig, evaluate_agreement


@one_line_errors("roboscape-eval-agreement")
def main(argv: list[str] | None = None):
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    cfg = draccus.parse(AgreementConfig, args=argv)
    evaluate_agreement(cfg)
    print((cfg.output_dir / "ladder.md").read_text())
    print(f"Results in {cfg.output_dir.resolve()}")


if __name__ == "__main__":
    main()
