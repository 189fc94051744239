"""PPO's learning rate on the bench: short PPO runs in `roboscape_maniskill` (one scene per family) from an SFT
checkpoint, one per (name, policy_lr, target_kl), printing each iteration's training success, return, approximate KL
and clip fraction (docs/results/bench/ppo_learning_rate.md).

    python scripts/experiments/ppo_lr_sweep.py \\
        --sft outputs/sft_curve/policies/shift_chunk8_exec4_gripper_demosall/15000 \\
        lr3e-4_kl0.05:3e-4:0.05 lr3e-5:3e-5:none lr1e-4:1e-4:none
"""

import argparse
from pathlib import Path

from lerobot_roboscape.experiments.trained import trained_stages
from lerobot_roboscape.pipeline import methods, policy_stages, stages
from lerobot_roboscape.pipeline.config import scale_config
from lerobot_roboscape.rl.configuration_ppo import PPOConfig
from lerobot_roboscape.rl.history import read_ppo_history
from lerobot_roboscape.rl.ppo import train_ppo


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", help="name:policy_lr:target_kl (target_kl 'none': off)")
    parser.add_argument("--sft", required=True, help="the SFT checkpoint PPO starts from")
    parser.add_argument("--run-dir", default="outputs/bench", help="the bench run (its demonstrations)")
    parser.add_argument("--iterations", type=int, default=6)
    args = parser.parse_args()
    p = scale_config("bench", (f"--output_dir={args.run_dir}",))
    out = Path(p.output_dir).resolve()
    t = trained_stages(p, out)
    wm = stages.world_model_env(p, t.demonstrations, t.tokenizer, t.models, t.done, t.reward_models)
    env = policy_stages.rl_envs(p, out, t.demonstrations, wm)[methods.RL_MANISKILL_ONE_SCENE]
    for run in args.runs:
        name, lr, kl = run.split(":")
        folder = out / "lr_sweep" / name
        train_ppo(
            PPOConfig(
                policy_path=str(Path(args.sft).resolve()),
                env=env,
                output_dir=folder,
                num_envs=p.ppo_envs,
                iterations=args.iterations,
                critic_warmup_iterations=1,
                policy_lr=float(lr),
                target_kl=None if kl == "none" else float(kl),
                device="cpu",
                save_freq=args.iterations,
            )
        )
        for r in read_ppo_history(folder):
            print(
                f"{name} {r.iteration} succ {r.success:.2f} ret {r.episode_return:.1f} "
                f"kl {r.logs.get('losses/approx_kl', 0):.3f} clip {r.logs.get('losses/clip_fraction', 0):.2f} "
                f"stop {int(r.logs.get('charts/update_stopped_by_kl', 0))}",
                flush=True,
            )


if __name__ == "__main__":
    main()
