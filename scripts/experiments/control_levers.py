"""Each lever of the world model's control path, measured by curves on the synthetic worlds.

`run` trains the tiny world model on one synthetic world with one variant of its config for a budget of training
minutes, reading retrieval (K = 4 action sequences over 4 steps from 32 starts; 2 instructions for text) every
`--eval-every` steps, and appends each point to OUT/<world>/<variant>.jsonl as it is measured. Each point also
reads the same model guided (scale 2 and 4) when the variant trains a null control: guidance needs no training of
its own. (The decoding orders, annealed and random, were read the same way, measured within noise of confidence and
removed; their columns stay in the saved curves.)

`report` draws OUT/control_levers.png and prints the table of every run (and of the drift runs).

`drift` trains the presets' combination with and without the anchor frame and corrupted context, per code or held
across the clip's frames (issue 72: the bench model's 100-step rollouts drifted) for `--steps`, reading retrieval
and, over rollouts of 32 frames (past the window of 5), the share of background cells kept, of the cells the square
uncovered kept, and of squares drawn where they are, into OUT/drift/.

`precision` trains the presets' combination on *motion* until it solves it, then reads the same model in float32,
under bf16 autocast (roboscape_wm's `precision`) and with one MaskGIT pass: retrieval over 64 starts, and the
share of float32's rollout tokens each keeps.

    python scripts/experiments/control_levers.py run --world motion --variant adaln_one_plus --minutes 10
    python scripts/experiments/control_levers.py report
    python scripts/experiments/control_levers.py drift --variant corrupt_anchor --seed 0 --steps 2000
    python scripts/experiments/control_levers.py precision --threads 2
"""

import argparse
import json
import time
from pathlib import Path

import torch

from lerobot_roboscape.world_model.modeling_world_model import STWorldModel
from lerobot_roboscape.world_model.synthetic import SyntheticWorld, drift, retrieval, train_on_world, world_model

OUT = Path("docs/results/world_model/control_levers")
WINDOW = 5  # the retrieval horizon (4) and its prompt frame
# The model as issue 36 found it: every lever off (the presets' defaults have moved since).
AS_BUILT = {"adaln": "none", "normalize_control": False, "control_dropout": 0.0}
COMBINED = {"adaln": "one_plus", "normalize_control": True, "normalize_actions": True, "control_dropout": 0.1}
LEVERS = {
    "as_built": {},
    # The new levers, each alone.
    "adaln_one_plus": {"adaln": "one_plus"},
    "normalize_control": {"normalize_control": True},
    "normalize_actions": {"normalize_actions": True},
    "control_dropout": {"control_dropout": 0.1},
    # The levers measured here alone and deleted (adaln_zero, full_mask, add_action, changed_token_weight,
    # context_drop): their curves stay in OUT/motion.
    # The combination, and each of its levers left out.
    "combined": COMBINED,
    **{f"combined_without_{k}": {n: v for n, v in COMBINED.items() if n != k} for k in COMBINED},
}
VARIANTS = {name: {**AS_BUILT, **levers} for name, levers in LEVERS.items()}
GUIDANCE = (2.0, 4.0)
PRESETS = {"adaln": "one_plus", "normalize_control": True, "normalize_actions": True}  # dropout off
DRIFT = {
    "preset": {},
    "anchor": {"anchor": True},
    "corrupt": {"corrupt_max": 0.2},
    "corrupt_anchor": {"corrupt_max": 0.2, "anchor": True},
    # corruption held across the clip's frames: only the anchor shows what it hides
    "held": {"corrupt_max": 0.2, "corrupt_held": True},
    "held_anchor": {"corrupt_max": 0.2, "corrupt_held": True, "anchor": True},
}
DRIFT_FRAMES = (1, 4, 8, 16, 32)  # the rollout frames a drift point keeps


def build_model(world: SyntheticWorld, variant: dict, seed: int = 0) -> STWorldModel:
    overrides = dict(variant)
    normalize = overrides.pop("normalize_actions", False)
    return world_model(world, WINDOW, seed, normalize_actions=normalize, **overrides)


def guided_retrievals(model: STWorldModel, world: SyntheticWorld) -> dict:
    """Retrieval of the same model guided, when it has a null control."""
    config, out = model.config, {}
    settings = {f"guidance_{g:g}": {"guidance_scale": g} for g in GUIDANCE} if config.control_dropout > 0 else {}
    for name, change in settings.items():
        saved = {k: getattr(config, k) for k in change}
        for k, v in change.items():
            setattr(config, k, v)
        out[f"retrieval_{name}"] = retrieval(model, world)[0]
        for k, v in saved.items():
            setattr(config, k, v)
    return out


def run(args):
    torch.set_num_threads(args.threads)
    world = SyntheticWorld(args.world)
    model = build_model(world, VARIANTS[args.variant], args.seed)
    path = args.out / args.world / f"{args.variant}.jsonl"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("")
    started = time.time()

    def on_eval(point, model):
        extra = guided_retrievals(model, world)
        line = {**point, **extra, "wall_minutes": (time.time() - started) / 60, "threads": args.threads}
        with path.open("a") as f:
            f.write(json.dumps(line) + "\n")
        print(args.world, args.variant, json.dumps(line), flush=True)
        return extra

    train_on_world(
        model,
        world,
        steps=10**9,
        batch_size=args.batch_size,
        seed=args.seed,
        eval_every=args.eval_every,
        minutes=args.minutes,
        on_eval=on_eval,
        until=args.until,
    )


def report(args):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    worlds = [w for w in ("wiring", "motion", "text") if (args.out / w).is_dir()]
    fig, axes = plt.subplots(2, len(worlds), figsize=(7 * len(worlds), 9), squeeze=False)
    columns = ["world", "variant", "steps", "minutes", "at 5 min", "at 10 min", "at 600 / 1,000 / 1,200 steps"]
    columns += ["first >= 0.9 (step, min)"]
    print("| " + " | ".join(columns + ["last: annealed / random / guided"]) + " |")
    print("|---|---|---:|---:|---:|---:|---:|---:|---|")
    for column, world in enumerate(worlds):
        measured = {p.stem for p in (args.out / world).glob("*.jsonl")}
        names = [*[v for v in VARIANTS if v in measured], *sorted(measured - set(VARIANTS))]
        colors = dict(zip(names, plt.cm.tab20.colors, strict=False))
        for name in names:
            path = args.out / world / f"{name}.jsonl"
            if not path.read_text().strip():
                continue
            curve = [json.loads(line) for line in path.read_text().splitlines()]
            style = "-" if name.startswith("combined") or name == "as_built" else "--"
            for row, x in enumerate(("minutes", "step")):
                axes[row, column].plot(
                    [p[x] for p in curve], [p["retrieval"] for p in curve], style, color=colors[name], label=name
                )

            def at(minutes, curve=curve, key="minutes"):
                before = [p for p in curve if p[key] <= minutes + 0.05]
                return f"{before[-1]['retrieval']:.2f}" if before and curve[-1][key] >= minutes else "-"

            end = f"{curve[-1]['retrieval']:.2f}" if curve[-1]["minutes"] >= 9.9 else "-"  # the budget's end
            at_steps = " / ".join(at(n, key="step") for n in (600, 1000, 1200))

            first = next((p for p in curve if p["retrieval"] >= 0.9), None)
            reached = f"{first['step']}, {first['minutes']:.1f}" if first else "never"
            last = curve[-1]
            others = " / ".join(f"{k[10:]} {v:.2f}" for k, v in last.items() if k.startswith("retrieval_"))
            print(
                f"| {world} | {name} | {last['step']} | {last['minutes']:.1f} | {at(5)} | {end} | {at_steps} "
                f"| {reached} "
                f"| {others} |"
            )
        for row, x in enumerate(("training minutes", "steps")):
            ax = axes[row, column]
            ax.axhline(0.25, color="grey", lw=0.5)
            ax.set(title=f"{world}: retrieval (K=4, 4 steps, 32 starts)", xlabel=x, ylabel="retrieval", ylim=(0, 1.02))
            ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(args.out / "control_levers.png", dpi=70)
    drift_table(args.out / "drift")


def drift_table(folder: Path):
    """Each drift run's readings: retrieval, then past the window the background kept, the cells the square
    uncovered kept, and the squares drawn where they are (printed, and drawn against steps in drift.png)."""
    if not folder.is_dir():
        return
    import matplotlib.pyplot as plt

    names = ("retrieval", "background_past_window", "uncovered_past_window", "square_past_window")
    fig, axes = plt.subplots(1, len(names), figsize=(5 * len(names), 4))
    for i, path in enumerate(sorted(folder.glob("*.jsonl"))):
        curve = [json.loads(line) for line in path.read_text().splitlines()]
        variant, seed = path.stem.rsplit("_seed", 1)
        for ax, name in zip(axes, names, strict=True):
            style = "-" if "anchor" in variant else "--"
            ax.plot([p["step"] for p in curve], [p[name] for p in curve], style, color=f"C{i // 2}", label=path.stem)
            ax.set(title=name.replace("_", " "), xlabel="steps")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(folder / "drift.png", dpi=70)
    print("\n| variant | seed | step | retrieval | background | uncovered | square | square, frame 1 / 8 / 32 |")
    print("|---|---:|---:|---:|---:|---:|---:|---|")
    for path in sorted(folder.glob("*.jsonl")):
        variant, seed = path.stem.rsplit("_seed", 1)
        for p in map(json.loads, path.read_text().splitlines()):
            past = " | ".join(f"{p[f'{name}_past_window']:.3f}" for name in ("background", "uncovered", "square"))
            frames = " / ".join(f"{p[f'square_{t}']:.2f}" for t in (1, 8, 32))
            print(f"| {variant} | {seed} | {p['step']} | {p['retrieval']:.2f} | {past} | {frames} |")


def drift_run(args):
    torch.set_num_threads(args.threads)
    world = SyntheticWorld("motion")
    model = build_model(world, {**AS_BUILT, **PRESETS, **DRIFT[args.variant]}, args.seed)
    path = args.out / "drift" / f"{args.variant}_seed{args.seed}.jsonl"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("")

    def on_eval(point, model):
        kept = drift(model, world)
        extra = {f"{name}_{t}": kept[name][t - 1] for name in kept for t in DRIFT_FRAMES}
        extra |= {f"{name}_past_window": sum(kept[name][WINDOW:]) / len(kept[name][WINDOW:]) for name in kept}
        with path.open("a") as f:
            f.write(json.dumps({**point, **extra}) + "\n")
        print(args.variant, args.seed, json.dumps({**point, **extra}), flush=True)
        return extra

    train_on_world(model, world, steps=args.steps, seed=args.seed, eval_every=args.eval_every, on_eval=on_eval)


def precision(args):
    torch.set_num_threads(args.threads)
    world = SyntheticWorld("motion")
    model = build_model(world, {**AS_BUILT, **PRESETS}, args.seed)
    trained = train_on_world(model, world, steps=10**9, eval_every=args.eval_every, minutes=args.minutes, until=0.97)
    print(f"trained: {trained[-1]}")
    reads = {"float32": ("float32", 2), "bfloat16": ("bfloat16", 2), "one pass": ("float32", 1)}
    rollouts = {}
    for name, (dtype, passes) in reads.items():
        model.config.maskgit_steps = passes
        with torch.autocast("cpu", torch.bfloat16, enabled=dtype == "bfloat16"):
            accuracy, rollouts[name], _ = retrieval(model, world, starts=64)
        kept = (rollouts[name] == rollouts["float32"]).mean()
        print(f"{name:>9}: retrieval {accuracy:.3f}, float32's tokens kept {kept:.4f}")


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("command", choices=["run", "report", "drift", "precision"])
    parser.add_argument("--world", default="motion", choices=["wiring", "motion", "text"])
    parser.add_argument("--variant", default="as_built", choices=[*VARIANTS, *DRIFT])
    parser.add_argument("--steps", type=int, default=2000, help="drift: training steps")
    parser.add_argument("--minutes", type=float, default=10.0, help="training minutes (evaluation not counted)")
    parser.add_argument("--eval-every", type=int, default=100)
    parser.add_argument("--until", type=float, default=0.98, help="stop once two evaluations in a row reach this")
    parser.add_argument("--batch-size", type=int, default=16)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    {"run": run, "report": report, "drift": drift_run, "precision": precision}[args.command](args)


if __name__ == "__main__":
    main()
