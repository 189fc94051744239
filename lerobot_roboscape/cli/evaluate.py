"""`roboscape-eval`: success rate of a policy in the ManiSkill simulator, IND and OOD, per task family.

roboscape-eval --policy_path=outputs/ppo/checkpoints/last/pretrained_model --episodes=50 --output_dir=outputs/eval
"""

import logging

import draccus

from lerobot_roboscape.cli import one_line_errors
from lerobot_roboscape.evaluation.success_rate import EvalConfig, evaluate_success


@one_line_errors("roboscape-eval")
def main(argv: list[str] | None = None):
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    cfg = draccus.parse(EvalConfig, args=argv)
    evaluate_success(cfg)
    print((cfg.output_dir / "eval.md").read_text())
    print(f"Results in {cfg.output_dir.resolve()}")


if __name__ == "__main__":
    main()
