"""`roboscape-push`: a dataset, the world models or a policy to the Hugging Face Hub, with its card.

    roboscape-push --artifact=dataset --repo_id=me/roboscape_demos --dataset_root=outputs/datasets/roboscape
    roboscape-push --artifact=world_models --repo_id=me/roboscape_world_models \\
        --tokenizer=outputs/tokenizer/pretrained_model \\
        --action_world_model=outputs/world_model_action/pretrained_model \\
        --text_world_model=outputs/world_model_text/pretrained_model --fidelity_dir=outputs/fidelity
    roboscape-push --artifact=policy --repo_id=me/roboscape_mlp_ppo_wm \\
        --policy=outputs/ppo/checkpoints/last/pretrained_model --eval_dir=outputs/eval

`--local_dir=DIR` writes the repo's folder under DIR instead of uploading (log in with `hf auth login` to upload).
"""

import logging
from dataclasses import dataclass
from pathlib import Path

import draccus

from lerobot_roboscape.cli import one_line_errors
from lerobot_roboscape.errors import InvalidInputError
from lerobot_roboscape.hub.push import push_dataset, push_policy, push_world_models

ARTIFACTS = ("dataset", "world_models", "policy")


@dataclass
class PushConfig:
    """Args:
    artifact: "dataset", "world_models" or "policy".
    repo_id: the Hub repo, `user_or_org/name`.
    local_dir: write the repo's folder under this directory instead of uploading.
    private: create the repo private (default: the Hub's default).
    dataset_root: (dataset) the LeRobotDataset directory.
    tokenizer: (world_models) the tokenizer's pretrained_model directory.
    action_world_model: (world_models) the action world model's pretrained_model directory.
    text_world_model: (world_models) the text world model's pretrained_model directory.
    fidelity_dir: (world_models) a roboscape-eval-wm report to publish with them.
    dataset_repo_id: (world_models, policy) the dataset they were trained on, as named on the Hub (default: the one
        in their training config).
    policy: (policy) a pretrained_model directory of lerobot-train or roboscape-ppo.
    eval_dir: (policy) a roboscape-eval output whose success table goes into the card.
    """

    artifact: str = "policy"
    repo_id: str = ""
    local_dir: Path | None = None
    private: bool | None = None
    dataset_root: Path | None = None
    tokenizer: Path | None = None
    action_world_model: Path | None = None
    text_world_model: Path | None = None
    fidelity_dir: Path | None = None
    dataset_repo_id: str | None = None
    policy: Path | None = None
    eval_dir: Path | None = None

    def __post_init__(self):
        if self.artifact not in ARTIFACTS:
            raise InvalidInputError(f"--artifact must be one of {ARTIFACTS}, got {self.artifact!r}")
        if self.repo_id.count("/") != 1:
            raise InvalidInputError(f"--repo_id must be `user_or_org/name`, got {self.repo_id!r}")
        needed = {
            "dataset": ["dataset_root"],
            "world_models": ["tokenizer", "action_world_model", "text_world_model"],
            "policy": ["policy"],
        }[self.artifact]
        missing = [f"--{name}" for name in needed if getattr(self, name) is None]
        if missing:
            raise InvalidInputError(f"--artifact={self.artifact} needs {', '.join(missing)}")


def push(cfg: PushConfig) -> str:
    if cfg.artifact == "dataset":
        return push_dataset(cfg.dataset_root, cfg.repo_id, cfg.local_dir, cfg.private)
    if cfg.artifact == "world_models":
        return push_world_models(
            cfg.repo_id,
            cfg.local_dir,
            cfg.private,
            tokenizer=cfg.tokenizer,
            action_world_model=cfg.action_world_model,
            text_world_model=cfg.text_world_model,
            dataset_repo_id=cfg.dataset_repo_id,
            fidelity_dir=cfg.fidelity_dir,
        )
    return push_policy(
        cfg.repo_id, cfg.policy, cfg.local_dir, cfg.private, eval_dir=cfg.eval_dir, dataset_repo_id=cfg.dataset_repo_id
    )


@one_line_errors("roboscape-push")
def main(argv: list[str] | None = None):
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    print(f"Pushed to {push(draccus.parse(PushConfig, args=argv))}")


if __name__ == "__main__":
    main()
