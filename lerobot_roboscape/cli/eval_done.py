"""`roboscape-eval-done`: which done signal to trust (the action model's head or a success classifier) and at
which threshold, chosen on validation episodes and measured on held-out ones.

    roboscape-eval-done --dataset.repo_id=local/roboscape_heldout --dataset.root=outputs/datasets/roboscape_heldout \
        --validation.repo_id=local/roboscape_validation --validation.root=outputs/datasets/roboscape_validation \
        --tokenizer=outputs/tokenizer/pretrained_model --world_model=outputs/world_model_action/pretrained_model \
        --success_classifier=outputs/reward_success/pretrained_model --output_dir=outputs/done_report
"""

import logging

import draccus

from lerobot_roboscape.cli import one_line_errors
from lerobot_roboscape.reward.done_report import DoneReportConfig, evaluate_done


@one_line_errors("roboscape-eval-done")
def main(argv: list[str] | None = None):
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    cfg = draccus.parse(DoneReportConfig, args=argv)
    evaluate_done(cfg)
    print((cfg.output_dir / "done_report.md").read_text())
    print(f"Report in {cfg.output_dir.resolve()}: done_report.md, done_report.json, done_curves.png")


if __name__ == "__main__":
    main()
