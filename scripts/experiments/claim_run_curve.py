"""The claim's runs in the world model read before the simulator's have run (issue 72: PPO's clock sized by the world
model run's curve): PPO in the world model and in each lever's variant of it (`--levers`), run here if not complete
(the simulator's PPO runs wait for the experiment), then the simulator success (OOD) of each run's checkpoints and
its rollouts in the world model replayed in the simulator, as the experiment's "checkpoint curve" and "replay" steps
make them and into the same folders, so that the experiment's rerun reads them instead of running them again. Takes
the experiment's own flags (a rerun of PPO with a larger `--pipeline.ppo.time_budget_s` goes on from there). Writes
run_curve.json (the plain run), run_curve_<lever>.json (each lever's) and run_curve.png (the simulator's points
beside the done the world model gave PPO's training episodes) into --report_dir.

    python scripts/experiments/claim_run_curve.py --protocol=paper --pipeline.scale=bench \
        --pipeline.output_dir=outputs/bench --pipeline.ppo.time_budget_s=3600 --pipeline.reward_ablation=false
"""

import json
import sys
from dataclasses import asdict
from pathlib import Path

from lerobot_roboscape.experiments.curves import checkpoint_curves
from lerobot_roboscape.experiments.experiment import Experiment, ExperimentConfig, lever_context, sft_policy
from lerobot_roboscape.experiments.levers import lever_runs
from lerobot_roboscape.experiments.replay import replay_in_simulator
from lerobot_roboscape.io.atomic import write_text_atomically
from lerobot_roboscape.pipeline import layout, methods, policy_stages
from lerobot_roboscape.pipeline.config import parse_config
from lerobot_roboscape.pipeline.report.figures import gaming_figure


def main():
    cfg = parse_config(ExperimentConfig, sys.argv[1:], "pipeline.")
    e, p = Experiment.of(cfg), cfg.pipeline
    policy, sft = next(iter(sft_policy(cfg, e.out, e.trained.demonstrations).items()))
    wm_env = e.world_model_env()
    context = lever_context(cfg, e.run, e.out, e.trained, wm_env)
    levers = lever_runs(cfg.levers, context, cfg.lever)
    envs = {methods.RL_WORLD_MODEL: context.world_model} | {method: run.env for method, run in levers.items()}
    rl = policy_stages.rl(p, e.out, e.trained.demonstrations, wm_env, {policy: sft}, levers, only=list(envs))[policy]
    curves = checkpoint_curves(cfg, e.out, e.trained.demonstrations, policy, sft, list(envs))
    report = Path(cfg.report_dir)
    report.mkdir(parents=True, exist_ok=True)
    for method, env in envs.items():
        for point in curves[method]:
            print(method, json.dumps(point))
        replays = replay_in_simulator(
            p,
            e.out / layout.replay_dir(method),
            env,
            rl[method],
            episodes=cfg.replay_rollouts,
            per_outcome=cfg.replay_episodes,
        )
        called = [r for r in replays if r.world_model_success]
        confirmed = sum(r.simulator_success for r in called)
        print(f"{method} replay: {len(replays)} runs; of the world model's {len(called)} successes, {confirmed} real")
        record = {"method": method, "curve": curves[method], "replays": [asdict(r) for r in replays]}
        name = "run_curve.json" if method == methods.RL_WORLD_MODEL else f"run_curve_{method.tag}.json"
        write_text_atomically(report / name, json.dumps(record, indent=2))
    gaming_figure(e.out, policy, curves, report / "run_curve.png")


if __name__ == "__main__":
    main()
