"""`roboscape-reward-report`: every reward type along held-out trajectories (paper Fig. 3) and how well each
separates successful from failed episodes.

    roboscape-reward-report --dataset.repo_id=local/heldout --dataset.root=outputs/datasets/heldout \
        --env.tokenizer=outputs/tokenizer/pretrained_model --env.action_world_model=outputs/wm_action/pretrained_model \
        --env.text_world_model=outputs/wm_text/pretrained_model \
        --embedding_reward=outputs/reward_embedding/pretrained_model \
        --proxy_reward=outputs/reward_proxy/pretrained_model
"""

import logging

import draccus

from lerobot_roboscape.cli import one_line_errors
from lerobot_roboscape.envs.reward_report import RewardReportConfig, auc_text, write_reward_report


@one_line_errors("roboscape-reward-report")
def main(argv: list[str] | None = None):
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    cfg = draccus.parse(RewardReportConfig, args=argv)
    report = write_reward_report(cfg)
    for kind, summary in report["summary"].items():
        print(f"{kind:18s} {auc_text(summary)} of the return")
    print(f"Report in {cfg.output_dir.resolve()}: reward_report.md, reward_report.json, reward_curves.png")


if __name__ == "__main__":
    main()
