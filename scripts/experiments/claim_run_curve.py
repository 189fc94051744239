"""One PPO run of the claim's experiment read before the others have run (issue 72: PPO's clock sized by the world
model run's curve): the simulator success (OOD) of its checkpoints, and its rollouts in the world model replayed in
the simulator, as the experiment's "checkpoint curve" and "replay" steps make them and into the same folders, so
that the experiment's rerun reads them instead of running them again. Takes the experiment's own flags; run it
once the run's PPO is complete (a rerun of PPO with a larger `--pipeline.ppo.time_budget_s` goes on from there).
Writes run_curve.json and run_curve.png (the simulator's points beside the done the world model gave PPO's
training episodes) into --report_dir.

    python scripts/experiments/claim_run_curve.py --protocol=paper --pipeline.scale=bench \
        --pipeline.output_dir=outputs/bench --pipeline.ppo.time_budget_s=3600 --pipeline.reward_ablation=false
"""

import json
import sys
from dataclasses import asdict
from pathlib import Path

from lerobot_roboscape.io.atomic import write_text_atomically
from lerobot_roboscape.pipeline import layout, methods, policy_stages
from lerobot_roboscape.pipeline.config import parse_config
from lerobot_roboscape.pipeline.curves import checkpoint_curves
from lerobot_roboscape.pipeline.experiment import Experiment, ExperimentConfig, sft_policy
from lerobot_roboscape.pipeline.figures import gaming_figure
from lerobot_roboscape.pipeline.replay import replay_in_simulator
from lerobot_roboscape.training.checkpoints import FINAL, last_checkpoint


def main():
    cfg = parse_config(ExperimentConfig, sys.argv[1:], "pipeline.")
    e, p = Experiment.of(cfg), cfg.pipeline
    (policy, sft), method = next(iter(sft_policy(cfg, e.out, e.trained.demonstrations).items())), methods.RL_WORLD_MODEL
    run = e.out / layout.rl_dir(policy, method)
    if last_checkpoint(run) is None:
        raise SystemExit(f"{run} holds no checkpoint: run the experiment's PPO first")
    curve = checkpoint_curves(cfg, e.out, e.trained.demonstrations, policy, sft, [method])[method]
    for point in curve:
        print(json.dumps(point))
    env = policy_stages.rl_envs(p, e.out, e.trained.demonstrations, e.world_model_env())[method]
    replays = replay_in_simulator(
        p,
        e.out / layout.replay_dir(method),
        env,
        last_checkpoint(run) / FINAL,
        episodes=cfg.replay_rollouts,
        per_outcome=cfg.replay_episodes,
    )
    called = [r for r in replays if r.world_model_success]
    confirmed = sum(r.simulator_success for r in called)
    print(f"replay: {len(replays)} runs; of the world model's {len(called)} successes, {confirmed} in the simulator")
    report = Path(cfg.report_dir)
    report.mkdir(parents=True, exist_ok=True)
    record = {"method": method, "curve": curve, "replays": [asdict(r) for r in replays]}
    write_text_atomically(report / "run_curve.json", json.dumps(record, indent=2))
    gaming_figure(e.out, policy, {method: curve}, report / "run_curve.png")


if __name__ == "__main__":
    main()
