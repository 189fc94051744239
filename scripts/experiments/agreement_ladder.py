"""The world model's agreement with the simulator over a ladder of policies (issue 72): `roboscape_mlp` SFT'd by
`lerobot-train` on the demonstrations of the first 1 and 8 training scenes (the first is the paper protocol's
initial scene), a checkpoint every fifth of its steps, beside the policies the claim's experiment trained in RUN
(each --protocols' SFT, the last checkpoint of each of its PPO runs, or those --runs names) and any given with
--policies; then `roboscape-eval-agreement` over them all on RUN's world models as the experiment builds its env, in
each of --splits: IND, OOD, or the paper protocol's initial scene alone (`initial`, its IND). The
ladder's ranking counts only over the most rungs the simulator tells apart (their 95% intervals disjoint, ladder.json's
`apart`), and this prints the agreement targets.

    python scripts/experiments/agreement_ladder.py outputs/bench --out outputs/bench/ladder --episodes 50
"""

import argparse
import json
from pathlib import Path

from lerobot_roboscape.evaluation.agreement import AgreementConfig, evaluate_agreement
from lerobot_roboscape.experiments.trained import trained_stages
from lerobot_roboscape.pipeline import layout, methods, policy_stages, stages
from lerobot_roboscape.pipeline.config import scale_config
from lerobot_roboscape.pipeline.lerobot_cli import lerobot_sft
from lerobot_roboscape.pipeline.report.world_model_targets import agreement_targets
from lerobot_roboscape.tasks import select_scenes
from lerobot_roboscape.training.checkpoints import CHECKPOINTS, FINAL, LAST

POLICY = "roboscape_mlp"
INITIAL = "initial"  # the split of the paper protocol's IND: its initial scene


def sft_rungs(cfg, demonstrations, out: Path, scene_counts: list[int], steps: int, checkpoints: int) -> list[Path]:
    """SFT of `steps` on the first k training scenes for each k, `checkpoints` checkpoints evenly over its steps
    (the last among them): every checkpoint, fewest scenes and steps first."""
    args = policy_stages.policy_specs(cfg)[POLICY]
    every = max(steps // checkpoints, 1)
    rungs = []
    for k in scene_counts:
        scenes = [s.id for s in select_scenes("ind")[:k]]
        folder = out / f"sft_{k}_scenes"
        lerobot_sft(folder, demonstrations, args, steps, cfg.sft.batch_size, save_freq=every, scenes=scenes)
        rungs += sorted(p / FINAL for p in (folder / CHECKPOINTS).iterdir() if p.name != LAST)
    return rungs


def experiment_rungs(run: Path, protocols: list[str], names: list[str] | None) -> list[Path]:
    """What the claim's experiment trained in `run`, where it has: each protocol's SFT and its PPO runs' last
    checkpoints (of the runs `names`; None: of every run)."""
    rungs = []
    for protocol in protocols:
        folder = run / layout.protocol_dir(protocol)
        sft = folder / layout.sft_dir(POLICY) / FINAL
        ppo = sorted((folder / layout.RL_DIR / POLICY).glob(f"*/{CHECKPOINTS}/*/{FINAL}"))
        last = {p.parents[2]: p for p in ppo if names is None or p.parents[2].name in names}  # each run's newest
        rungs += [p for p in (sft, *last.values()) if p.exists()]
    return rungs


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path, help="a pipeline run's output folder (its world models, done report, data)")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--scale", default="bench")
    parser.add_argument("--scenes", type=int, nargs="*", default=[1, 8], help="SFT rungs: on the first k scenes")
    parser.add_argument("--sft_steps", type=int, help="steps of the SFT rungs' runs (default: the scale's)")
    parser.add_argument("--checkpoints", type=int, default=5, help="SFT checkpoints per rung's run")
    parser.add_argument(
        "--protocols", nargs="*", default=list(methods.PROTOCOLS), help="the protocols whose runs are rungs"
    )
    parser.add_argument("--runs", nargs="*", help="the experiment's PPO runs taken as rungs (default: all)")
    parser.add_argument("--policies", nargs="*", default=[], help="more rungs: pretrained_model folders")
    parser.add_argument(
        "--splits",
        nargs="+",
        default=["ind", "ood"],
        choices=[INITIAL, "ind", "ood"],
        help=f"{INITIAL}: new initial states in the paper protocol's initial scene alone",
    )
    parser.add_argument("--episodes", type=int, default=50, help="paired episodes per family and policy")
    args = parser.parse_args()
    run, out = args.run.resolve(), args.out.resolve()
    cfg = scale_config(args.scale, (f"--output_dir={run}",))
    trained = trained_stages(cfg, run)
    steps = args.sft_steps or cfg.sft.steps
    sft = sft_rungs(cfg, trained.demonstrations, out, args.scenes, steps, args.checkpoints)
    rungs = [*sft, *experiment_rungs(run, args.protocols, args.runs), *args.policies]
    env = stages.world_model_env(
        cfg, trained.demonstrations, trained.tokenizer, trained.models, trained.done, trained.reward_models
    )
    for split in args.splits:
        ladder = evaluate_agreement(
            AgreementConfig(
                policy_paths=[str(p) for p in rungs],
                env=env,
                families=cfg.data.families,
                split="ind" if split == INITIAL else split,
                scenes=[methods.initial_scene()] if split == INITIAL else [],
                episodes=args.episodes,
                episode_length=cfg.eval.episode_length,
                output_dir=out / split,
                device=cfg.device,
            )
        )
        for name, target in agreement_targets(ladder, split=split).items():
            print(json.dumps({"target": name, **target}))


if __name__ == "__main__":
    main()
