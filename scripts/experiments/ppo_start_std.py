"""The sampled policy PPO starts from against the deterministic one evaluation scores: success of an SFT checkpoint
in `roboscape_maniskill` (IND) when its Gaussian's std is each of `--stds` (0: the mean, as `roboscape-eval` acts),
every std on the same initial states, so the differences are paired (issue 100).

    python scripts/experiments/ppo_start_std.py --sft carried/bench72_run/sft_mlp/pretrained_model \\
        --stds 0 0.05 0.1 0.22 --episodes 32 --out docs/results/ppo_sim/start_std.json
"""

import argparse
import json
import math
from pathlib import Path

import numpy as np
import torch

from lerobot_roboscape.envs.configs import RoboscapeManiSkillEnvConfig
from lerobot_roboscape.evaluation.results import paired_difference_interval
from lerobot_roboscape.rl.policy_loading import PolicyIO, load_policy
from lerobot_roboscape.rl.rollout import collect_rollout


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sft", required=True)
    parser.add_argument("--stds", type=float, nargs="+", default=[0.0, 0.05, 0.1, 0.22])
    parser.add_argument("--episodes", type=int, default=32, help="per std, over both families")
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--seed", type=int, default=300_000)
    parser.add_argument("--workers", type=int, default=None)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    env_cfg = RoboscapeManiSkillEnvConfig(
        families=["pick_place", "push"], split="ind", episode_length=100, workers=args.workers
    )
    env = env_cfg.create_envs(args.batch)[env_cfg.type][0]
    policy, pre, post = load_policy(args.sft, "cpu")
    policy.eval()
    io = PolicyIO(pre, post)
    outcomes = {}
    for std in args.stds:
        policy.action_log_std.data.fill_(math.log(max(std, 1e-8)))
        torch.manual_seed(0)
        runs = [
            collect_rollout(env, policy, io, seed=args.seed + k).successes
            for k in range(math.ceil(args.episodes / args.batch))
        ]
        outcomes[std] = np.concatenate(runs)
        print(f"std {std}: success {outcomes[std].mean():.3f} over {len(outcomes[std])} episodes", flush=True)
    env.close()
    base = outcomes[args.stds[0]]
    rows = []
    for std, success in outcomes.items():
        _, low, high = paired_difference_interval(list(success), list(base))
        rows.append(
            {
                "std": std,
                "success": float(success.mean()),
                "episodes": len(success),
                "pick_place": float(success[0::2].mean()),
                "push": float(success[1::2].mean()),
                "minus_first": float(success.mean() - base.mean()),
                "paired_95": [low, high],
            }
        )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"sft": args.sft, "seed": args.seed, "rows": rows}, indent=1))
    print(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
