"""The figures behind the RL objective, measured on data the project collects itself (CPU, about 30 minutes):

1. the done head's false positives on held-out failed attempts, for an action world model trained on successes
   only (as before failed attempts were collected) and for one trained on failures too, same steps;
2. the episode return of held-out successful and failed episodes under the default `roboscape_wm` reward
   (Algorithm 1: fixed horizon, sparse reward at every step while done >= theta_sps, dense reward from the
   similarity to the goal frame of the text world model), with the world model trained on failures.

Every stage writes its outputs under --output_dir and is skipped when they exist, so a killed run picks up where
it stopped. Prints the figures and writes them to summary.json.

    python scripts/measure_rl_objective.py --output_dir=outputs/rl_objective
"""

import argparse
import json
from pathlib import Path

from lerobot.configs.default import DatasetConfig

from lerobot_roboscape.checkpoints import FINAL
from lerobot_roboscape.demos.collect import CollectConfig, collect
from lerobot_roboscape.envs.configs import RoboscapeWorldModelEnvConfig
from lerobot_roboscape.envs.reward_report import RewardReportConfig, write_reward_report
from lerobot_roboscape.tokenizer.configuration_tokenizer import TinyTokenizerConfig
from lerobot_roboscape.tokenizer.train import TokenizerTrainingConfig, TrainTokenizerConfig, train_tokenizer
from lerobot_roboscape.world_model.configuration_world_model import TinyWorldModelConfig
from lerobot_roboscape.world_model.fidelity import FidelityConfig, evaluate_fidelity
from lerobot_roboscape.world_model.train import TrainWorldModelConfig, WorldModelTrainingConfig, train_world_model

FAMILIES = ["pick_place", "push"]


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--output_dir", type=Path, default=Path("outputs/rl_objective"))
    parser.add_argument("--scenes", type=int, default=4, help="IND scenes of the training collection")
    parser.add_argument("--episodes_per_scene", type=int, default=4)
    parser.add_argument("--heldout_scenes", type=int, default=3, help="OOD scenes of the held-out collection")
    parser.add_argument("--tokenizer_steps", type=int, default=400)
    parser.add_argument("--wm_steps", type=int, default=400)
    args = parser.parse_args()
    out = args.output_dir

    datasets = {
        "train": CollectConfig(
            repo_id="local/rl_objective_train",
            root=str(out / "train"),
            families=FAMILIES,
            split="ind",
            max_scenes=args.scenes,
            episodes_per_scene=args.episodes_per_scene,
            failed_fraction=0.25,
            seed=0,
        ),
        "heldout": CollectConfig(
            repo_id="local/rl_objective_heldout",
            root=str(out / "heldout"),
            families=FAMILIES,
            split="ood",
            max_scenes=args.heldout_scenes,
            episodes_per_scene=2,
            failed_fraction=0.5,
            seed=50_000,
        ),
    }
    for cfg in datasets.values():
        if not (Path(cfg.root) / "meta" / "info.json").is_file():
            collect(cfg)
    train = DatasetConfig(repo_id="local/rl_objective_train", root=str(out / "train"))
    heldout = DatasetConfig(repo_id="local/rl_objective_heldout", root=str(out / "heldout"))

    tokenizer = out / "tokenizer" / FINAL
    if not tokenizer.is_dir():
        train_tokenizer(
            TrainTokenizerConfig(
                dataset=train,
                tokenizer=TinyTokenizerConfig(image_size=64),
                train=TokenizerTrainingConfig(steps=args.tokenizer_steps, save_freq=args.tokenizer_steps),
                output_dir=tokenizer.parent,
                num_workers=1,
                allow_random_lpips=True,
            )
        )

    # Same data, same steps: the action model of successes only (before) and of every attempt (after).
    models = {
        "action_successes_only": ("action", True),
        "action_with_failures": ("action", False),
        "text": ("text", None),
    }
    for name, (control, only_successful) in models.items():
        if not (out / name / FINAL).is_dir():
            train_world_model(
                TrainWorldModelConfig(
                    dataset=train,
                    tokenizer=str(tokenizer),
                    wm=TinyWorldModelConfig(control=control),
                    train=WorldModelTrainingConfig(steps=args.wm_steps, save_freq=args.wm_steps),
                    output_dir=out / name,
                    cache_dir=out / "token_cache",
                    only_successful=only_successful,
                    device="cpu",
                )
            )

    summary = {"done_false_positive": {}, "returns": {}}
    for name in ("action_successes_only", "action_with_failures"):
        report_dir = out / f"fidelity_{name}"
        if not (report_dir / "fidelity.json").is_file():
            evaluate_fidelity(
                FidelityConfig(
                    dataset=heldout,
                    tokenizer=str(tokenizer),
                    world_model=str(out / name / FINAL),
                    output_dir=report_dir,
                    allow_random_lpips=True,
                    device="cpu",
                )
            )
        report = json.loads((report_dir / "fidelity.json").read_text())
        summary["done_false_positive"][name] = report["done_false_positive"]

    if not (out / "reward_report" / "reward_report.json").is_file():
        write_reward_report(
            RewardReportConfig(
                env=RoboscapeWorldModelEnvConfig(
                    tokenizer=str(tokenizer),
                    action_world_model=str(out / "action_with_failures" / FINAL),
                    text_world_model=str(out / "text" / FINAL),
                    similarity="tokenizer",
                    device="cpu",
                ),
                dataset=heldout,
                output_dir=out / "reward_report",
                max_episodes=64,
            )
        )
    rewards = json.loads((out / "reward_report" / "reward_report.json").read_text())
    summary["returns"] = {"similarity": rewards["similarity"], **rewards["summary"]}

    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    print("done head on held-out failed attempts (done probability >= its threshold):")
    for name, fp in summary["done_false_positive"].items():
        if fp is None:
            print(f"  {name:24s} no failed episode held out")
            continue
        print(
            f"  {name:24s} frames (teacher-forced) {fp['frames_teacher_forced']['rate']:.3f}, frames (open loop) "
            f"{fp['frames_open_loop']['rate']:.3f}, episodes {fp['episodes']['flagged']}/{fp['episodes']['total']}"
        )
    print(f"episode returns under the default roboscape_wm reward ({summary['returns']['similarity']} similarity):")
    for kind, s in rewards["summary"].items():
        print(
            f"  {kind:18s} success {s['mean_return_success']}, failure {s['mean_return_failure']}, "
            f"ROC-AUC {s['roc_auc_of_return']}"
        )


if __name__ == "__main__":
    main()
