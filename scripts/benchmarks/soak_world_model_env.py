"""Soak of `roboscape_wm`: a batch of 64 episodes stepped for 300+ steps with random actions, resetting whenever
every episode has ended. Prints the process's resident memory (RSS) along the way, and fails if an observation or
reward is ever not finite. Flat memory means nothing grows with the steps (the KV cache slides, the goal cache is
bounded by the starts).

Uses the models and dataset of a pipeline run (`roboscape-demo`: tiny models; --demo-dir=outputs/bench: the bench
scale's 16x16-grid models).

    python scripts/benchmarks/soak_world_model_env.py --demo-dir outputs/bench --batch-size 64 --steps 300
"""

import argparse
import time
from pathlib import Path

import numpy as np
import psutil
import torch

from lerobot_roboscape.envs.configs import RoboscapeWorldModelEnvConfig
from lerobot_roboscape.envs.world_model_env import RoboscapeWorldModelEnv


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--demo-dir", type=Path, default=Path("outputs/demo"))
    parser.add_argument("--batch-size", type=int, default=64)
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--episode-length", type=int, default=50)
    parser.add_argument("--every", type=int, default=25, help="steps between two memory readings")
    parser.add_argument("--image-size", type=int, default=64, help="the models' camera image side")
    args = parser.parse_args()
    demo = args.demo_dir
    if not (demo / "world_model_action" / "pretrained_model").is_dir():
        raise SystemExit(f"no demo models under {demo}: run `roboscape-demo` first (or pass --demo-dir)")
    torch.manual_seed(0)
    config = RoboscapeWorldModelEnvConfig(
        dataset_repo_id="local/roboscape_demos",
        dataset_root=str(demo / "datasets" / "roboscape_demos"),
        tokenizer=str(demo / "tokenizer" / "pretrained_model"),
        action_world_model=str(demo / "world_model_action" / "pretrained_model"),
        text_world_model=str(demo / "world_model_text" / "pretrained_model"),
        image_size=args.image_size,
        allow_random_lpips=True,
        episode_length=args.episode_length,
        temperature=1.0,
    )
    env = RoboscapeWorldModelEnv(config, num_envs=args.batch_size)
    process, rng = psutil.Process(), np.random.default_rng(0)
    print(
        f"torch {torch.__version__}, {torch.get_num_threads()} CPU threads, batch {args.batch_size}, "
        f"{args.steps} steps, episodes of {args.episode_length} steps"
    )
    print(f"{'step':>6} {'RSS MiB':>9} {'resets':>7} {'s/step':>7}")
    env.reset(seed=0)
    resets, started, readings = 1, time.perf_counter(), {}
    for step in range(1, args.steps + 1):
        obs, reward, terminated, truncated, _ = env.step(rng.uniform(-1, 1, env.action_space.shape).astype(np.float32))
        if not np.isfinite(reward).all():
            raise SystemExit(f"step {step}: reward not finite: {reward}")
        if (terminated | truncated).all():
            env.reset()
            resets += 1
        if step == 1 or step % args.every == 0:
            readings[step] = process.memory_info().rss / 2**20
            rate = (time.perf_counter() - started) / step
            print(f"{step:>6} {readings[step]:>9.1f} {resets:>7} {rate:>7.3f}")
    later = [rss for step, rss in readings.items() if step >= 100]
    print(
        f"RSS at step 1: {readings[1]:.1f} MiB; from step 100 to {args.steps}: {min(later):.1f}-{max(later):.1f} "
        f"MiB (growth {max(later) - later[0]:+.1f} MiB)"
    )


if __name__ == "__main__":
    main()
