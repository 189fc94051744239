"""SFT learning curve and policy-habit ablation: simulator success of `roboscape_mlp` after `lerobot-train`, against
the demonstrations per scene, the training steps and the policy's habits.

Each run trains once on the first `demos` successful demonstrations of every (family, scene) of the dataset and
saves a checkpoint every `steps / checkpoints` steps; every checkpoint is evaluated in the simulator (IND, and the
splits asked for at the last one) with `roboscape-eval`'s code, so a run gives its curve in steps for the cost of
one training. An evaluation-only habit (executing a chunk, a binary gripper) is evaluated on a copy of a trained
checkpoint whose config says so, without training again.

    python scripts/experiments/sft_curve.py --dataset outputs/bench/datasets/roboscape_demos --out outputs/sft_curve \
        --runs shift:all shift:8 --steps 6000 --checkpoints 3 --episodes 50 --final_splits ind ood

A run is VARIANT:DEMOS (DEMOS per scene, or "all"); finished trainings and evaluations are not redone. The table
(sft_curve.md), the figure (sft_curve.png) and every number (sft_curve.json) are written under --out.

    python scripts/experiments/sft_curve.py --targets outputs/sft_curve/eval/<run>/<steps>/eval.json \
        --out docs/results/sft

writes the bench report's SFT target rows of one evaluation (IND, with OOD beside) to results.json, and

    python scripts/experiments/sft_curve.py --merge outputs/sft_habits/sft_curve.json \
        outputs/sft_curve/sft_curve.json --out DIR

one table and figure of several runs' sft_curve.json.
"""

import argparse
import json
import shutil
import time
from pathlib import Path

# Policy habits, by name, each spelled out in full (the policy's defaults are the kept ones). A variant trains with
# its habits; an evaluation-only variant (a different gripper or chunk execution) reuses the checkpoints of the
# variant it was trained as, with its evaluation habits written into a copy of the config.
HABITS = ("random_shift_pad", "chunk_size", "n_action_steps", "binary_gripper")
EVAL_HABITS = ("n_action_steps", "binary_gripper")
VARIANTS = {
    "baseline": (0, 1, 1, False),  # the bench's MLP before the SFT issue
    "shift": (4, 1, 1, False),
    "shift_gripper": (4, 1, 1, True),
    "shift_chunk8": (4, 8, 1, False),
    "shift_chunk8_gripper": (4, 8, 1, True),
    "shift_chunk8_exec4_gripper": (4, 8, 4, True),  # the policy's defaults
}
TRAINED_AS = {
    "shift_gripper": "shift",
    "shift_chunk8_gripper": "shift_chunk8",
    "shift_chunk8_exec4_gripper": "shift_chunk8",
}


def habits(variant: str) -> dict:
    return dict(zip(HABITS, VARIANTS[variant], strict=True))


def parse_run(run: str) -> tuple[str, int | None]:
    variant, _, demos = run.partition(":")
    if variant not in VARIANTS:
        raise SystemExit(f"unknown variant {variant!r}; known: {sorted(VARIANTS)}")
    return variant, None if demos in ("", "all") else int(demos)


def run_name(variant: str, demos: int | None) -> str:
    return f"{variant}_demos{'all' if demos is None else demos}"


def train(args, variant: str, demos: int | None) -> tuple[Path, float]:
    from lerobot.configs.default import DatasetConfig

    from lerobot_roboscape.pipeline.lerobot_cli import lerobot_sft
    from lerobot_roboscape.pipeline.resume import stage_seconds

    folder = Path(args.out) / "train" / run_name(TRAINED_AS.get(variant, variant), demos)
    lerobot_sft(
        folder,
        DatasetConfig(repo_id="local/roboscape_demos", root=args.dataset),
        [
            "--policy.type=roboscape_mlp",
            "--policy.device=cpu",
            f"--seed={args.seed}",
            *(f"--policy.{k}={str(v).lower()}" for k, v in habits(TRAINED_AS.get(variant, variant)).items()),
        ],
        args.steps,
        args.batch_size,
        num_workers=2,
        per_scene=demos,
        save_freq=args.steps // args.checkpoints,
    )
    return folder, stage_seconds(folder) or 0.0


def with_eval_options(checkpoint: Path, changes: dict, where: Path) -> Path:
    """A copy of `checkpoint` whose config carries `changes` (the weights and processors unchanged)."""
    if not changes:
        return checkpoint
    if not (where / "config.json").exists():
        tmp = where.with_name(where.name + ".tmp")
        shutil.rmtree(tmp, ignore_errors=True)
        shutil.copytree(checkpoint, tmp)
        config = json.loads((tmp / "config.json").read_text()) | changes
        (tmp / "config.json").write_text(json.dumps(config, indent=2))
        tmp.rename(where)
    return where


def evaluate(args, checkpoint: Path, out: Path, splits: list[str]) -> dict:
    from lerobot_roboscape.evaluation.success_rate import EVAL_JSON, EvalConfig, evaluate_success

    if (out / EVAL_JSON).exists():
        return json.loads((out / EVAL_JSON).read_text())
    cfg = EvalConfig(
        policy_path=str(checkpoint),
        families=args.families,
        splits=splits,
        episodes=args.episodes,
        batch_size=8,
        workers=2,
        videos=8,
        output_dir=out,
        device="cpu",
        resume=True,
    )
    return evaluate_success(cfg)


def run(args, variant: str, demos: int | None) -> list[dict]:
    folder, seconds = train(args, variant, demos)
    name = run_name(variant, demos)
    rows = []
    for step in range(args.steps // args.checkpoints, args.steps + 1, args.steps // args.checkpoints):
        checkpoint = folder / "checkpoints" / f"{step:06d}" / "pretrained_model"
        last = step == args.steps
        trained = habits(TRAINED_AS.get(variant, variant))
        changes = {k: v for k, v in habits(variant).items() if k in EVAL_HABITS and v != trained[k]}
        policy = with_eval_options(checkpoint, changes, Path(args.out) / "policies" / name / str(step))
        started, before = time.time(), len(rows)
        result = evaluate(
            args, policy, Path(args.out) / "eval" / name / str(step), args.final_splits if last else ["ind"]
        )
        for split, cells in result["splits"].items():
            for family, cell in cells.items():
                rows.append(
                    {
                        "variant": variant,
                        "demos_per_scene": "all" if demos is None else demos,
                        "steps": step,
                        "split": split,
                        "family": family,
                        **cell,
                        "train_minutes": round(seconds / 60, 1),
                    }
                )
        print(f"{name} step {step}: {summarise(rows[before:])} ({time.time() - started:.0f} s)")
    return rows


def summarise(rows: list[dict]) -> str:
    return ", ".join(f"{r['split']} {r['family']} {r['successes']}/{r['episodes']}" for r in rows)


def markdown(rows: list[dict]) -> str:
    lines = [
        "| variant | demos/scene | steps | split | family | success | 95% CI | train min |",
        "|---|---|---:|---|---|---:|---:|---:|",
    ]
    for r in rows:
        low, high = r["ci95"]
        lines.append(
            f"| {r['variant']} | {r['demos_per_scene']} | {r['steps']} | {r['split'].upper()} | {r['family']} | "
            f"{r['successes']}/{r['episodes']} ({r['success_rate']:.0%}) | {low:.0%}-{high:.0%} | "
            f"{r['train_minutes']} |"
        )
    return "\n".join(lines) + "\n"


def figure(rows: list[dict], path: Path) -> None:
    """Top: IND success against SFT steps, one line per variant and data size. Bottom: against demonstrations
    per scene, one line per variant and step count measured at more than one data size."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    families = sorted({r["family"] for r in rows if r["family"] != "all"})
    fig, axes = plt.subplots(2, len(families), figsize=(5 * len(families), 7.2), squeeze=False)
    sizes = sorted({r["demos_per_scene"] for r in rows}, key=lambda d: float("inf") if d == "all" else d)
    for column, family in enumerate(families):
        ind = [r for r in rows if r["family"] == family and r["split"] == "ind"]
        for ax, x, group in ((axes[0, column], "steps", "demos_per_scene"), (axes[1, column], "demos", "steps")):
            curves = {}
            for r in ind:
                curves.setdefault((r["variant"], r[group]), []).append(r)
            for (variant, value), points in sorted(curves.items(), key=str):
                if x == "demos" and len(points) < 2:
                    continue
                points.sort(key=lambda r: r["steps"] if x == "steps" else sizes.index(r["demos_per_scene"]))
                xs = [r["steps"] if x == "steps" else sizes.index(r["demos_per_scene"]) for r in points]
                line = ax.plot(xs, [r["success_rate"] for r in points], marker="o")[0]
                line.set_label(f"{variant}, {value}/scene" if x == "steps" else f"{variant}, {value} steps")
                low, high = zip(*(r["ci95"] for r in points), strict=True)
                ax.fill_between(xs, low, high, color=line.get_color(), alpha=0.12)
            ax.set(title=f"{family}: IND success", ylabel="success rate", ylim=(0, 1))
            if x == "steps":
                ax.set_xlabel("SFT steps")
            else:
                ax.set(xlabel="demonstrations per scene", xticks=range(len(sizes)), xticklabels=sizes)
            if ax.lines:
                ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_targets(eval_json: Path, out: Path) -> None:
    from lerobot_roboscape.pipeline.methods import SFT
    from lerobot_roboscape.pipeline.report.targets import sft_targets

    result = json.loads(eval_json.read_text())
    families = [family for family in result["splits"]["ind"] if family != "all"]
    targets = sft_targets({"roboscape_mlp": {SFT: result["splits"]}}, families)
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(json.dumps({"evaluation": result["policy"], "targets": targets}, indent=2))
    print(json.dumps(targets, indent=2))


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--dataset")
    parser.add_argument("--out", default="outputs/sft_curve")
    parser.add_argument("--runs", nargs="+", default=[], help="VARIANT:DEMOS_PER_SCENE (or VARIANT:all)")
    parser.add_argument("--targets", type=Path, help="an eval.json: write its SFT target rows and stop")
    parser.add_argument("--merge", type=Path, nargs="+", help="sft_curve.json files: one table and figure of all")
    parser.add_argument("--families", nargs="+", default=["push", "pick_place"])
    parser.add_argument("--steps", type=int, default=6000)
    parser.add_argument("--checkpoints", type=int, default=3, help="evaluated checkpoints, evenly spaced")
    parser.add_argument("--batch_size", type=int, default=32)
    parser.add_argument("--episodes", type=int, default=50, help="per family and split")
    parser.add_argument("--final_splits", nargs="+", default=["ind"])
    parser.add_argument("--seed", type=int, default=1000)
    args = parser.parse_args()
    if args.targets:
        return write_targets(args.targets, Path(args.out))
    if args.merge:
        return write_all([row for path in args.merge for row in json.loads(path.read_text())], Path(args.out))
    if not args.dataset or not args.runs:
        parser.error("--dataset and --runs are required to train and evaluate")

    out = Path(args.out)
    everything = out / "sft_curve.json"
    rows = json.loads(everything.read_text()) if everything.exists() else []
    for spec in args.runs:
        variant, demos = parse_run(spec)
        new = run(args, variant, demos)
        keys = {(r["variant"], r["demos_per_scene"], r["steps"], r["split"], r["family"]) for r in new}
        rows = [
            r for r in rows if (r["variant"], r["demos_per_scene"], r["steps"], r["split"], r["family"]) not in keys
        ]
        rows += new
        write_all(rows, out)


def write_all(rows: list[dict], out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / "sft_curve.json").write_text(json.dumps(rows, indent=1))
    (out / "sft_curve.md").write_text(markdown(rows))
    figure(rows, out / "sft_curve.png")
    print(markdown(rows))


if __name__ == "__main__":
    main()
