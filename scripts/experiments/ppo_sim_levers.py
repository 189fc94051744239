"""PPO where the truth is known (issue 100): PPO in `roboscape_maniskill` over every training scene from the
all-scene SFT policy, one run per (lever, seed) at the same PPO clock, each judged by its checkpoint curve of
deterministic success in the simulator (IND, the same initial states at every point) and a paired last cell.
`--protocol=scene`: then the same PPO in the world model (`roboscape_wm`, the 2-core models in carried/bench72)
from the paper protocol's one-scene SFT, starting from its demonstrations of the initial scene, judged there.

    python scripts/experiments/ppo_sim_levers.py train --lever grpo --seed 0 --minutes 15 --workers 1
    python scripts/experiments/ppo_sim_levers.py curve --lever grpo --seed 0 --episodes 8
    python scripts/experiments/ppo_sim_levers.py cell --lever grpo --seed 0 --episodes 50   # also: --lever sft
    python scripts/experiments/ppo_sim_levers.py report --report docs/results/ppo_sim

A run's folder is outputs/ppo_sim/<lever>_seed<seed>; a rerun skips what is complete.
"""

import argparse
import json
import shutil
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from lerobot_roboscape.envs.configs import RoboscapeManiSkillEnvConfig, RoboscapeWorldModelEnvConfig  # noqa: E402
from lerobot_roboscape.evaluation.results import paired_difference_interval  # noqa: E402
from lerobot_roboscape.evaluation.success_rate import EVAL_JSON, EvalConfig, evaluate_success, read_cells  # noqa: E402
from lerobot_roboscape.experiments.done_refresh import DoneRefresh, ppo_with_done_refresh  # noqa: E402
from lerobot_roboscape.rl.configuration_ppo import PPOConfig  # noqa: E402
from lerobot_roboscape.rl.history import read_ppo_history  # noqa: E402
from lerobot_roboscape.rl.ppo import train_ppo  # noqa: E402
from lerobot_roboscape.rl.ppo_state import checkpoint_seconds  # noqa: E402
from lerobot_roboscape.training.checkpoints import CHECKPOINTS, FINAL, PPO_CONFIG_JSON  # noqa: E402

FAMILIES = ["pick_place", "push"]
HORIZON = 100
CURVE_SEED, CELL_SEED = 400_000, 100_000  # the curve's starts; the last cell's (Table 1's)
INITIAL_SCENE = "red_cube-plate-wooden"  # the paper protocol's one scene
CARRIED = Path("carried")
SCENE_SFT = CARRIED / "bench72_run/protocol_paper/sft_mlp/pretrained_model"
NUM_ENVS = 16  # episodes per PPO iteration, 8 per family; GRPO: 4 groups of 4 from one start
THETA = 0.9106324911117554  # the done threshold the bench's done stage chose (carried/bench72/action/done_tuning.json)
# Every lever over today's PPO (PPO_DEFAULTS["roboscape_mlp"]) at 16 parallel episodes per iteration. At std 0.1
# one iteration of today's update moved the policy 0.15-0.41 nats (clip fraction 0.56-0.77, the first try): each
# lever stops its update at an approximate KL of 0.02.
LEVERS = {
    "plain": {},
    "std": dict(init_std=0.1, target_kl=0.02),
    "std_warmup": dict(init_std=0.1, target_kl=0.02, critic_warmup_iterations=6),
    "grpo": dict(advantage="group", group_size=4, init_std=0.1, target_kl=0.02),
    "grpo_kl": dict(advantage="group", group_size=4, init_std=0.1, target_kl=0.02, kl_coef=0.1),
    # In the world model the KL stop bounds each update, not their sum (the scene's std run drifted 81% -> 56%).
    "std_kl": dict(init_std=0.1, target_kl=0.02, kl_coef=0.1),
    # GRPO's iterations swung 0-69% sampled success on 2 starts a family: 8 starts a family, at 4x the episodes.
    "grpo_wide": dict(advantage="group", group_size=4, init_std=0.1, target_kl=0.02, num_envs=64),
}
# In the world model the done fired in 1 of 100 iterations where SFT succeeds in 63% of the scene's episodes:
# std_kl with the done head refitted on 16 simulator episodes of the current policy in the scene before each of 3
# slices of the run (experiments/done_refresh.py).
LEVERS["std_kl_refresh"] = LEVERS["std_kl"]
REFRESHED = {"std_kl_refresh"}
# The same GRPO continued past its 400 episodes (`train --lever grpo_long --extend grpo --iterations 75`): its run
# starts as a copy of the grpo run's folder, so the first 25 iterations and their curve are shared, not replayed.
LEVERS["grpo_long"] = LEVERS["grpo"]


def run_dir(out: Path, lever: str, seed: int) -> Path:
    return out / f"{lever}_seed{seed}"


def env_config(protocol: str, workers: int | None):
    if protocol == "all_scenes":
        return RoboscapeManiSkillEnvConfig(families=FAMILIES, split="ind", episode_length=HORIZON, workers=workers)
    models = CARRIED / "bench72"
    return RoboscapeWorldModelEnvConfig(
        dataset_repo_id="local/roboscape_sft_initial",
        dataset_root=str((CARRIED / "bench72_run/datasets/roboscape_sft_initial").resolve()),
        tokenizer=str((models / "tokenizer/pretrained_model").resolve()),
        action_world_model=str((models / "action/pretrained_model").resolve()),
        text_world_model=str((models / "text/pretrained_model").resolve()),
        families=FAMILIES,
        split="ind",
        scenes=[INITIAL_SCENE],
        starts_per_scene=16,
        theta=THETA,
        theta_sps=THETA,
        similarity="tokenizer",  # no LPIPS trunk here: a random one is no perceptual metric
        episode_length=HORIZON,
        goal_file=str(Path("outputs/ppo_wm_scene/goals.safetensors").resolve()),
    )


def train(args) -> None:
    folder = run_dir(args.out, args.lever, args.seed)
    if (folder / FINAL).exists():
        return
    if args.extend and not folder.exists():
        source = run_dir(args.out, args.extend, args.seed)
        # Not the run's final policy nor its last cell: they become this run's when it ends.
        top_only = lambda d, names: [n for n in names if Path(d) == source and n in (FINAL, "cell")]  # noqa: E731
        shutil.copytree(source, folder, symlinks=True, ignore=top_only)
    cfg = PPOConfig(
        policy_path=str(args.sft.resolve()),
        env=env_config(args.protocol, args.workers),
        output_dir=folder,
        iterations=args.iterations or 10_000,
        time_budget_s=None if args.iterations else args.minutes * 60,
        save_freq=args.save_freq,
        seed=args.seed,
        device="cpu",
        resume=(folder / CHECKPOINTS).exists(),
        **({"num_envs": NUM_ENVS} | LEVERS[args.lever]),
    )
    if args.lever in REFRESHED:
        ppo_with_done_refresh(cfg, refresh=scene_refresh(args.out, args.workers))
    else:
        train_ppo(cfg)


def scene_refresh(out: Path, workers: int | None) -> DoneRefresh:
    wm = env_config("scene", workers)
    return DoneRefresh(
        sim=RoboscapeManiSkillEnvConfig(
            families=FAMILIES, split="ind", scenes=[INITIAL_SCENE], episode_length=HORIZON, workers=workers
        ),
        tokenizer=wm.tokenizer,
        demonstrations_repo_id=wm.dataset_repo_id,
        demonstrations_root=wm.dataset_root,
        cache_dir=str((out / "token_cache").resolve()),
        rounds=3,
        episodes=16,
        device="cpu",
    )


def evaluate(policy: Path, output_dir: Path, episodes: int, seed: int, workers: int | None, scenes=()) -> dict:
    if not (output_dir / EVAL_JSON).exists():
        evaluate_success(
            EvalConfig(
                policy_path=str(policy),
                families=FAMILIES,
                splits=["ind"],
                scenes=list(scenes),
                episodes=episodes,
                batch_size=8,
                episode_length=HORIZON,
                seed=seed,
                videos=0,
                workers=workers,
                output_dir=output_dir,
                device="cpu",
                resume=output_dir.exists(),
            )
        )
    return read_cells(output_dir, "ind")


def episodes_per_iteration(folder: Path) -> int:
    # from a checkpoint's settings: a run stopped before its end has no final policy nor settings beside it
    return json.loads((checkpoints(folder)[-1] / PPO_CONFIG_JSON).read_text())["num_envs"]


def checkpoints(folder: Path) -> list[Path]:
    return sorted(p for p in (folder / CHECKPOINTS).iterdir() if p.name.isdigit())


def curve(args) -> None:
    """SFT (iteration 0) and every checkpoint of the run, on the same starts."""
    folder = run_dir(args.out, args.lever, args.seed)
    scenes = scenes_of(args.protocol)
    evaluate(args.sft.resolve(), args.out / "curve_sft", args.episodes, CURVE_SEED, args.workers, scenes)
    saved = checkpoints(folder)
    for checkpoint in sorted(set(saved[:: args.every] + saved[-1:])):
        output = folder / "curve" / checkpoint.name
        evaluate(checkpoint / FINAL, output, args.episodes, CURVE_SEED, args.workers, scenes)


def scenes_of(protocol: str) -> tuple[str, ...]:
    return () if protocol == "all_scenes" else (INITIAL_SCENE,)


def cell(args) -> None:
    if args.lever == "sft":
        policy, output = args.sft.resolve(), args.out / "cell_sft"
    elif args.policy is not None:  # a run made elsewhere (the simulator's PPO of the protocol), beside ours
        policy, output = args.policy.resolve(), args.out / f"cell_{args.lever}"
    else:
        folder = run_dir(args.out, args.lever, args.seed)
        policy, output = checkpoints(folder)[-1] / FINAL, folder / "cell"
    evaluate(policy, output, args.episodes, CELL_SEED, args.workers, scenes_of(args.protocol))


def read_curve(out: Path, folder: Path) -> list[dict]:
    points = [{"iteration": 0, "minutes": 0.0, "cells": read_cells(out / "curve_sft", "ind")}]
    for checkpoint in checkpoints(folder):
        if (folder / "curve" / checkpoint.name / EVAL_JSON).exists():
            points.append(
                {
                    "iteration": int(checkpoint.name),
                    "minutes": checkpoint_seconds(checkpoint) / 60,
                    "cells": read_cells(folder / "curve" / checkpoint.name, "ind"),
                }
            )
    return points


def report(args) -> None:
    args.report.mkdir(parents=True, exist_ok=True)
    runs = sorted(p for p in args.out.iterdir() if (p / CHECKPOINTS).is_dir())
    sft_cell = read_cells(args.out / "cell_sft", "ind") if (args.out / "cell_sft" / EVAL_JSON).exists() else None
    results, lines = {"sft_cell": None, "runs": {}}, []
    if sft_cell:
        results["sft_cell"] = {f: c.success_rate for f, c in sft_cell.items()}
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for folder in runs:
        points = read_curve(args.out, folder)
        history = read_ppo_history(folder)
        per_iteration = episodes_per_iteration(folder)
        entry = {
            "episodes_per_iteration": per_iteration,
            "curve": [
                {"iteration": p["iteration"], "minutes": round(p["minutes"], 2)}
                | {f: c.success_rate for f, c in p["cells"].items()}
                for p in points
            ],
            "episodes_per_point": points[0]["cells"]["all"].episodes,
            "iterations": history[-1].iteration if history else 0,
            "train_success_first_last5": [
                sum(r.success for r in history[:5]) / max(1, len(history[:5])),
                sum(r.success for r in history[-5:]) / max(1, len(history[-5:])),
            ],
        }
        if sft_cell and (folder / "cell" / EVAL_JSON).exists():
            entry["cell"] = minus_sft(read_cells(folder / "cell", "ind"), sft_cell)
        results["runs"][folder.name] = entry
        # By episodes played, not minutes: the seed-1 runs shared the cores with other runs.
        episodes = [p["iteration"] * per_iteration for p in points]
        axes[0].plot(episodes, [p["cells"]["all"].success_rate for p in points], marker="o", label=folder.name)
        axes[1].plot(
            [r.iteration * per_iteration for r in history], _smooth([r.success for r in history]), label=folder.name
        )
    where = "IND" if args.protocol == "all_scenes" else "initial scene"
    told = "sampled success" if args.protocol == "all_scenes" else "the world model's done"
    axes[0].set(xlabel="PPO episodes", ylabel=f"{where} success (simulator, 16 episodes)", title="checkpoint curve")
    axes[1].set(xlabel="PPO episodes", ylabel=f"{told} (5-iteration mean)", title="training")
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    for folder in sorted(args.out.glob("cell_*")):  # policies trained elsewhere (`cell --policy`), beside SFT
        if folder.name != "cell_sft" and sft_cell and (folder / EVAL_JSON).exists():
            results.setdefault("others", {})[folder.name] = minus_sft(read_cells(folder, "ind"), sft_cell)
    fig.tight_layout()
    fig.savefig(args.report / "curves.png", dpi=110)
    (args.report / "results.json").write_text(json.dumps(results, indent=1))
    for name, entry in results["runs"].items():
        per_iteration = entry["episodes_per_iteration"]
        curve_text = ", ".join(f"{p['iteration'] * per_iteration}: {p['all']:.0%}" for p in entry["curve"])
        lines.append(f"| {name} | {entry['iterations']} | {curve_text} |")
        for family, c in entry.get("cell", {}).items():
            lines.append(
                f"|  | cell {family} | {c['success']:.0%} vs SFT {c['sft']:.0%}: {c['minus_sft']:+.0%} "
                f"[{c['paired_95'][0]:+.0%}, {c['paired_95'][1]:+.0%}] ({c['episodes']} eps) |"
            )
    for name, cells in results.get("others", {}).items():
        lines += [
            f"| {name} | cell {f} | {c['success']:.0%}: {c['minus_sft']:+.0%} {c['paired_95']} |"
            for f, c in cells.items()
        ]
    print("\n".join(lines))


def minus_sft(ours: dict, sft_cell: dict) -> dict:
    """Per family: a cell's success beside SFT's on the same starts, and their paired difference."""
    cells = {}
    for family in ours:
        d, low, high = paired_difference_interval(list(ours[family].outcomes), list(sft_cell[family].outcomes))
        cells[family] = {
            "success": ours[family].success_rate,
            "sft": sft_cell[family].success_rate,
            "minus_sft": d,
            "paired_95": [low, high],
            "episodes": ours[family].episodes,
        }
    return cells


def _smooth(values: list[float], k: int = 5) -> list[float]:
    return [sum(values[max(0, i - k + 1) : i + 1]) / len(values[max(0, i - k + 1) : i + 1]) for i in range(len(values))]


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("step", choices=["train", "curve", "cell", "report"])
    parser.add_argument("--lever", default="plain", help=f"one of {sorted(LEVERS)} (cell: also 'sft')")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--protocol", choices=["all_scenes", "scene"], default="all_scenes")
    parser.add_argument("--sft", type=Path, default=None, help="default: the protocol's SFT in carried/")
    parser.add_argument("--policy", type=Path, default=None, help="cell: a policy trained elsewhere, as --lever")
    parser.add_argument("--out", type=Path, default=Path("outputs/ppo_sim"))
    parser.add_argument("--report", type=Path, default=Path("docs/results/ppo_sim"))
    parser.add_argument("--minutes", type=float, default=15.0)
    parser.add_argument("--iterations", type=int, default=None, help="train this many instead of --minutes")
    parser.add_argument("--extend", default=None, help="train: continue this lever's run of the same seed")
    parser.add_argument("--every", type=int, default=1, help="curve: every k-th checkpoint (and the last)")
    parser.add_argument("--save_freq", type=int, default=6)
    parser.add_argument("--episodes", type=int, default=8, help="per family")
    parser.add_argument("--workers", type=int, default=None)
    args = parser.parse_args()
    if args.sft is None:
        args.sft = SCENE_SFT if args.protocol == "scene" else CARRIED / "bench72_run/sft_mlp/pretrained_model"
    known = args.lever in LEVERS or (args.step == "cell" and (args.lever == "sft" or args.policy is not None))
    if args.step != "report" and not known:
        parser.error(f"--lever must be one of {sorted(LEVERS)}")
    {"train": train, "curve": curve, "cell": cell, "report": report}[args.step](args)


if __name__ == "__main__":
    main()
