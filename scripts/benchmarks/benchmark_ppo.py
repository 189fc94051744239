"""PPO throughput of the MLP policy in `roboscape_wm` (the demo's tiny world models) against
`roboscape_maniskill` (the simulator) at the same batch and image size: decisions/s of the rollout alone and of
whole PPO iterations (rollout + update). A decision is one look of the policy; it executes the chunk's
n_action_steps env steps (the MLP's default: 4), so env steps/s are up to that many times more. Needs a
`roboscape-demo` run (its SFT MLP and models).

    python scripts/benchmarks/benchmark_ppo.py --batch-sizes 8 16 --episode-length 40 --iterations 2
"""

import argparse
import time
from pathlib import Path

import torch

from lerobot_roboscape.envs.configs import RoboscapeManiSkillEnvConfig, RoboscapeWorldModelEnvConfig
from lerobot_roboscape.rl.configuration_ppo import PPOConfig
from lerobot_roboscape.rl.policy_loading import PolicyIO, load_policy
from lerobot_roboscape.rl.ppo import ActionScorer, make_optimizer, update
from lerobot_roboscape.rl.ppo_state import RunningReturnStats
from lerobot_roboscape.rl.rollout import collect_rollout


def measure(env_cfg, checkpoint: Path, batch_size: int, iterations: int) -> tuple[float, float]:
    """(decisions/s of the rollouts alone, decisions/s of whole iterations): a rollout's steps are the policy's
    decisions (collect_rollout), each up to n_action_steps env steps."""
    from accelerate import Accelerator

    policy, preprocessor, postprocessor = load_policy(str(checkpoint), "cpu")
    io = PolicyIO(preprocessor, postprocessor)
    cfg = PPOConfig(policy_path=str(checkpoint), env=env_cfg, num_envs=batch_size).with_policy_defaults(policy.name)
    accelerator = Accelerator(cpu=True)
    scorer, optimizer = accelerator.prepare(ActionScorer(policy), make_optimizer(policy, cfg))
    env = env_cfg.create_envs(batch_size)[env_cfg.type][0]
    collect_rollout(env, policy, io, seed=0)  # warm-up (goals of the world-model env are cached from here on)
    steps, rollout_s, total_s, stats = 0, 0.0, 0.0, RunningReturnStats()
    for i in range(iterations):
        torch.manual_seed(i)
        start = time.perf_counter()
        rollout = collect_rollout(env, policy, io, seed=i)
        rollout_s += time.perf_counter() - start
        update(cfg, accelerator, scorer, optimizer, io, rollout, torch.Generator().manual_seed(i), stats, False)
        total_s += time.perf_counter() - start
        steps += int(rollout.alive.sum())
    env.close()
    return steps / rollout_s, steps / total_s


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--demo-dir", type=Path, default=Path("outputs/demo"))
    parser.add_argument("--batch-sizes", type=int, nargs="+", default=[8, 16])
    parser.add_argument("--episode-length", type=int, default=40)
    parser.add_argument("--iterations", type=int, default=2)
    parser.add_argument("--image-size", type=int, default=64)
    args = parser.parse_args()
    demo = args.demo_dir.resolve()
    checkpoint = demo / "sft_mlp" / "checkpoints" / "last" / "pretrained_model"
    if not checkpoint.is_dir():
        raise SystemExit(f"no SFT MLP under {demo}: run `roboscape-demo` first (or pass --demo-dir)")
    wm = RoboscapeWorldModelEnvConfig(
        dataset_repo_id="local/roboscape_demos",
        dataset_root=str(demo / "datasets" / "roboscape_demos"),
        tokenizer=str(demo / "tokenizer" / "pretrained_model"),
        action_world_model=str(demo / "world_model_action" / "pretrained_model"),
        text_world_model=str(demo / "world_model_text" / "pretrained_model"),
        image_size=args.image_size,
        episode_length=args.episode_length,
        allow_random_lpips=True,
        device="cpu",
        max_goal_steps=40,
    )
    sim = RoboscapeManiSkillEnvConfig(image_size=args.image_size, episode_length=args.episode_length)
    print(
        f"PPO of the MLP policy, {args.image_size} px, 2 cameras, {args.episode_length}-step episodes, CPU "
        f"({torch.get_num_threads()} threads); decisions/s, each decision up to n_action_steps env steps"
    )
    print(
        "| batch | roboscape_wm rollout decisions/s | roboscape_wm PPO decisions/s | roboscape_maniskill rollout "
        "decisions/s | roboscape_maniskill PPO decisions/s | PPO ratio |\n|---:|---:|---:|---:|---:|---:|"
    )
    for batch_size in args.batch_sizes:
        wm_rollout, wm_total = measure(wm, checkpoint, batch_size, args.iterations)
        sim_rollout, sim_total = measure(sim, checkpoint, batch_size, args.iterations)
        print(
            f"| {batch_size} | {wm_rollout:.1f} | {wm_total:.1f} | {sim_rollout:.1f} | {sim_total:.1f} | "
            f"{wm_total / sim_total:.1f}x |",
            flush=True,
        )


if __name__ == "__main__":
    main()
