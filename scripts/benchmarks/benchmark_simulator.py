"""Where the simulator's time goes, and collection, evaluation and PPO in `roboscape_maniskill` beside today's path,
in one run.

"Today's path" is the code before issue 25, kept behind two settings: ManiSkill's own wrist-camera mesh
(`light_wrist_camera=False`) and every env in the caller's process (`workers=1`). The new path renders the light
mesh (tasks/wrist_camera_mesh.py) and spreads the envs over one worker process per core (envs/simulator_slots.py).
The policy is the roboscape_mlp at its default size with its processors (untrained: its cost is the same).

    python scripts/benchmarks/benchmark_simulator.py                    # profile, then the three benchmarks
    python scripts/benchmarks/benchmark_simulator.py --only profile eval
"""

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from lerobot_roboscape.tasks import SCENES

CAMERAS = ("observation.images.third_view", "observation.images.wrist")
PATHS = {"today": dict(light_wrist_camera=False, workers=1), "new": dict(light_wrist_camera=True, workers=None)}


def print_speed_up(rates: dict[str, float]) -> None:
    if len(rates) == 2:
        print(f"speed-up: {rates['new'] / rates['today']:.1f}x")


def timed(fn, *args, **kwargs) -> tuple[float, object]:
    start = time.perf_counter()
    out = fn(*args, **kwargs)
    return time.perf_counter() - start, out


def make_mlp_checkpoint(folder: Path, image_size: int) -> Path:
    """An untrained roboscape_mlp at its default size, saved with its processors (min-max actions over [-1, 1])."""
    from lerobot.configs.types import FeatureType, PolicyFeature
    from lerobot.policies.factory import make_pre_post_processors
    from lerobot_policy_roboscape_mlp import RoboscapeMLPConfig, RoboscapeMLPPolicy

    features = {key: PolicyFeature(FeatureType.VISUAL, (3, image_size, image_size)) for key in CAMERAS}
    config = RoboscapeMLPConfig(
        device="cpu", input_features=features, output_features={"action": PolicyFeature(FeatureType.ACTION, (7,))}
    )
    stats = {"action": {"min": -torch.ones(7), "max": torch.ones(7)}}
    pre, post = make_pre_post_processors(config, dataset_stats=stats)
    RoboscapeMLPPolicy(config).save_pretrained(folder)
    pre.save_pretrained(folder)
    post.save_pretrained(folder)
    return folder


# ---- profile ------------------------------------------------------------------------------------------------------


def render_pictures(task, uids: list[str]) -> None:
    """What a step renders: the scene's poses to the renderer, then each camera's picture, read back as RGB."""
    task.scene.update_render()
    for uid in uids:
        task._sensors[uid].capture()
    for uid in uids:
        task._sensors[uid].get_obs(rgb=True, depth=False, segmentation=False, position=False)


def profile(image_size: int, policy_path: Path, steps: int) -> None:
    from lerobot_roboscape.envs.configs import RoboscapeManiSkillEnvConfig
    from lerobot_roboscape.rl.policy_loading import PolicyIO, load_policy
    from lerobot_roboscape.tasks.make import make_task_env

    command = [sys.executable, "-c", "import lerobot_roboscape.evaluation.success_rate, lerobot_roboscape.rl.ppo"]
    start_up, _ = timed(subprocess.run, command, check=True, capture_output=True)
    print(f"\n## Profile (one process, torch with {torch.get_num_threads()} threads)")
    print(f"process start-up (python + imports of torch, lerobot, mani_skill): {start_up:.1f} s")
    print(
        f"{'wrist-camera mesh':>18} {'make env':>9} {'1st reset':>10} {'reset':>7} {'step':>7} {'physics':>8} "
        f"{'render both':>12} {'3rd view':>9} {'wrist':>7} {'resize':>7}"
    )
    action = np.zeros(7, np.float32)
    make_task_env("push", SCENES[0].id, image_size=image_size).close()  # the process's one-off renderer start-up
    for light in (False, True):
        make_s, env = timed(make_task_env, "push", SCENES[0].id, image_size=image_size, light_wrist_camera=light)
        first_s, _ = timed(env.reset, seed=0)
        reset_s = np.mean([timed(env.reset, seed=k)[0] for k in range(1, 4)])
        task = env.unwrapped
        sizes = {(s.config.width, s.config.height) for s in task._sensors.values()}
        assert sizes == {(image_size, image_size)}, f"cameras render at {sizes}, not the stored {image_size} px"
        for _ in range(3):
            env.step(action)
        step_s = np.mean([timed(env.step, action)[0] for _ in range(steps)])
        render = {
            name: np.mean([timed(render_pictures, task, uids)[0] for _ in range(steps)])
            for name, uids in (("both", list(task._sensors)), ("third", ["third_view"]), ("wrist", ["hand_camera"]))
        }
        env.close()
        print(
            f"{'light' if light else 'ManiSkill':>18} {make_s:>8.1f}s {first_s:>9.2f}s {reset_s:>6.2f}s "
            f"{1e3 * step_s:>5.0f}ms {1e3 * (step_s - render['both']):>6.0f}ms {1e3 * render['both']:>10.0f}ms "
            f"{1e3 * render['third']:>7.0f}ms {1e3 * render['wrist']:>5.0f}ms {'none':>7}"
        )
    print(
        f"(resize: none, both cameras render at the stored {image_size} px; physics = step - render both, which "
        "includes the controller, the reward and the observation)"
    )
    policy, pre, post = load_policy(str(policy_path), "cpu")
    io = PolicyIO(pre, post)
    pixels = {cam.split(".")[-1]: np.zeros((8, image_size, image_size, 3), np.uint8) for cam in CAMERAS}
    with torch.no_grad():
        io.env_action(policy.select_action(io.batch(pixels, ["push the red cube forward"] * 8)))
        policy_s = np.mean(
            [timed(lambda: io.env_action(policy.select_action(io.batch(pixels, ["x"] * 8))))[0] for _ in range(20)]
        )
    print(f"policy with its processors (roboscape_mlp, batch 8): {1e3 * policy_s:.1f} ms per batch step")
    workers = RoboscapeManiSkillEnvConfig().resolved_workers(8)
    mesa = os.environ.get("LP_NUM_THREADS", "unset: one per core")
    print(
        f"cores shared: a batch of 8 runs on {workers} simulator worker processes, each with torch's default threads "
        f"({torch.get_num_threads()}) and Mesa's (LP_NUM_THREADS={mesa}); the policy runs in this process while "
        "they wait"
    )


# ---- benchmarks ---------------------------------------------------------------------------------------------------


def bench_collect(tmp: Path, episodes: int, image_size: int) -> None:
    from lerobot_roboscape.demos import collect as collect_module
    from lerobot_roboscape.demos.collect import CollectConfig, collect

    print(f"\n## Collection: {episodes} pick&place planner episodes, 2 cameras stored, 2 worker processes")
    rates = {}
    run_jobs, write_dataset = collect_module.run_jobs, collect_module.write_dataset
    for name, path in PATHS.items():
        arrivals, writing = [], []  # (seconds, frames) of each episode as the workers hand it over; the write

        def timed_jobs(*args, arrivals=arrivals, **kwargs):
            for episode in run_jobs(*args, **kwargs):
                arrivals.append((time.perf_counter(), len(episode.action)))
                yield episode

        def timed_write(*args, writing=writing, **kwargs):
            seconds, dataset = timed(write_dataset, *args, **kwargs)
            writing.append(seconds)
            return dataset

        collect_module.run_jobs, collect_module.write_dataset = timed_jobs, timed_write
        cfg = CollectConfig(
            root=str(tmp / f"collect_{name}"),
            families=["pick_place"],
            max_scenes=episodes,
            episodes_per_scene=1,
            failed_fraction=0.0,
            suboptimal_fraction=0.0,
            image_size=image_size,
            workers=2,
            light_wrist_camera=path["light_wrist_camera"],
        )
        start = time.perf_counter()
        seconds, dataset = timed(collect, cfg)
        rates[name] = dataset.meta.total_frames / seconds
        # Steady state: the episodes after each worker's first (which carries its start-up), until the last.
        steady = sum(frames for _, frames in arrivals[2:]) / (arrivals[-1][0] - arrivals[1][0])
        print(
            f"{name:>6}: {dataset.meta.total_frames} frames in {seconds:.0f} s: {rates[name]:.1f} frames/s; start-up "
            f"to the first episode {arrivals[0][0] - start:.0f} s, then {steady:.1f} frames/s, then "
            f"{writing[0]:.0f} s writing the dataset (video encoding in the main process)"
        )
    collect_module.run_jobs, collect_module.write_dataset = run_jobs, write_dataset
    print_speed_up(rates)


def bench_eval(policy_path: Path, image_size: int, batches: int, episode_length: int) -> None:
    from lerobot_roboscape.envs.configs import RoboscapeManiSkillEnvConfig
    from lerobot_roboscape.envs.maniskill_env import RoboscapeManiSkillEnv
    from lerobot_roboscape.evaluation.success_rate import run_episodes
    from lerobot_roboscape.rl.policy_loading import PolicyIO, load_policy

    policy, pre, post = load_policy(str(policy_path), "cpu")
    io = PolicyIO(pre, post)
    print(
        f"\n## Evaluation: batch 8, {batches} batches of {episode_length}-step episodes (pick&place and push, IND "
        "scenes), the policy included"
    )
    rates = {}
    for name, path in PATHS.items():
        cfg = RoboscapeManiSkillEnvConfig(
            families=["pick_place", "push"], image_size=image_size, episode_length=episode_length, **path
        )
        build_s, env = timed(RoboscapeManiSkillEnv, cfg, num_envs=8)
        run_s, _ = timed(lambda env=env: [run_episodes(env, policy, io, seed=k) for k in range(batches)])
        env.close()
        steps = 8 * batches * episode_length
        rates[name] = steps / run_s
        print(
            f"{name:>6} ({cfg.resolved_workers(8)} process{'es' if cfg.resolved_workers(8) > 1 else ''}): "
            f"{rates[name]:.1f} env steps/s ({steps} steps and {batches} resets in {run_s:.0f} s), envs built in "
            f"{build_s:.0f} s; with the build: {steps / (run_s + build_s):.1f} env steps/s"
        )
    print_speed_up(rates)


def bench_ppo(policy_path: Path, image_size: int, num_envs: int, iterations: int, episode_length: int) -> None:
    from benchmark_ppo import measure  # the PPO throughput of scripts/benchmarks/benchmark_ppo.py, beside this file
    from lerobot_policy_roboscape_mlp import RoboscapeMLPConfig

    from lerobot_roboscape.envs.configs import RoboscapeManiSkillEnvConfig

    print(
        f"\n## PPO in roboscape_maniskill: {num_envs} envs, {iterations} iterations of {episode_length} steps "
        f"(after a warm-up rollout); a decision executes {RoboscapeMLPConfig().n_action_steps} env steps"
    )
    rates = {}
    for name, path in PATHS.items():
        env_cfg = RoboscapeManiSkillEnvConfig(
            families=["pick_place", "push"], image_size=image_size, episode_length=episode_length, **path
        )
        rollout_rate, rates[name] = measure(env_cfg, policy_path, num_envs, iterations)
        print(f"{name:>6}: {rates[name]:.1f} decisions/s of rollout + update ({rollout_rate:.1f} of rollout alone)")
    print_speed_up(rates)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--only", nargs="+", default=["profile", "collect", "eval", "ppo"])
    parser.add_argument("--paths", nargs="+", default=list(PATHS), help="today's path, the new one, or both")
    parser.add_argument("--image-size", type=int, default=64)
    parser.add_argument("--profile-steps", type=int, default=30)
    parser.add_argument("--collect-episodes", type=int, default=24)
    parser.add_argument("--eval-batches", type=int, default=2)
    parser.add_argument("--episode-length", type=int, default=100)
    parser.add_argument("--ppo-envs", type=int, default=8)
    parser.add_argument("--ppo-iterations", type=int, default=2)
    args = parser.parse_args()
    for name in set(PATHS) - set(args.paths):
        del PATHS[name]
    print(
        f"{os.cpu_count()} CPU cores, {args.image_size} px, 2 cameras; today = ManiSkill's wrist-camera mesh, 1 process"
    )
    with tempfile.TemporaryDirectory(prefix="roboscape-simulator-") as tmp:
        tmp = Path(tmp)
        policy_path = make_mlp_checkpoint(tmp / "mlp", args.image_size)
        if "profile" in args.only:
            profile(args.image_size, policy_path, args.profile_steps)
        if "collect" in args.only:
            bench_collect(tmp, args.collect_episodes, args.image_size)
        if "eval" in args.only:
            bench_eval(policy_path, args.image_size, args.eval_batches, args.episode_length)
        if "ppo" in args.only:
            bench_ppo(policy_path, args.image_size, args.ppo_envs, args.ppo_iterations, args.episode_length)


if __name__ == "__main__":
    main()
