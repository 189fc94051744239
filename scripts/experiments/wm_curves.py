"""Held-out curves of world-model runs side by side against training minutes, from each run's heldout_curve.jsonl: of
the action model, retrieval (whole frame, object, by state), action gain and the measures that see the arm (the
TCP's error, the arm region's PSNR, the motion ratio) on each controllability set (`roboscape-train-wm
--heldout_control...` or `--heldout_starts=[ind.safetensors,ood.safetensors]`, whose measures are named `ind/...`,
`ood/...`); of the text model, its goals on each goal set (`--heldout_goals`, wm_levers.py's `text` runs). Writes
OUT/NAME.png (a row per set, a column per measure; runs named `<lever>_seed<n>` share a colour per lever, a line style
per seed) and OUT/NAME.json (every run's curve), and prints markdown tables of each run at every point and at its
last.

    python scripts/experiments/wm_curves.py outputs/screen/levers/*_seed* --out docs/results/world_model/levers70
"""

import argparse
import json
import re
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from lerobot_roboscape.training.loop import read_curve  # noqa: E402

MEASURES = {
    "retrieval_whole_frame": "retrieval, whole frame (K = 4)",
    "retrieval_object": "retrieval, object region",
    "retrieval_state": "retrieval by state",
    "action_gain_db": "action gain (dB)",
    "likelihood_retrieval": "retrieval from the likelihood",
    "tcp_error_share_of_moved": "TCP error / distance moved (median)",
    "arm_psnr": "arm region PSNR (dB)",
    "motion_ratio": "motion ratio",
    "scene_psnr_in_window": "scene PSNR, start in the window (dB)",
    "scene_psnr_past_window": "scene PSNR, past the window (dB)",
    "arm_psnr_past_window": "arm region PSNR, past the window (dB)",
    "goal_reached": "goals: done crosses theta in the horizon",
    "goal_nearer_final": "goal nearer the success than the start",
    "goal_done_max": "goals: highest done (median)",
    "goal_steps_share": "goals: control steps to the goal / horizon (median)",
}
GOALS = {
    "retrieval_whole_frame": 0.9,
    "retrieval_state": 0.95,
    "action_gain_db": 3.0,
    "tcp_error_share_of_moved": 0.15,
    "motion_ratio": 1.0,
    "goal_reached": 0.7,
    "goal_nearer_final": 0.8,
}


def split(key: str) -> tuple[str, str]:
    """'ind/retrieval_state' -> ('ind', 'retrieval_state'); an unprefixed measure is the run's own set ('')."""
    return tuple(key.split("/", 1)) if "/" in key else ("", key)


def named(point: dict, subset: str) -> dict:
    """The point with its unprefixed measures named as read on `subset` ('' leaves them as they are)."""
    if not subset:
        return point
    return {f"{subset}/{k}" if "/" not in k and k in MEASURES else k: v for k, v in point.items()}


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", type=Path, nargs="+", help="output_dir of each roboscape-train-wm run")
    parser.add_argument("--out", type=Path, default=Path("docs/results/world_model"))
    parser.add_argument("--name", default="wm_curves")
    parser.add_argument("--x", choices=("minutes", "steps"), default="minutes", help="steps: for runs not timed alone")
    parser.add_argument("--cores", default="one core", help="what each run trained on, for the minutes' label")
    parser.add_argument(
        "--unprefixed", default="", help="the set a run's unprefixed measures were read on (a pipeline run's: ood)"
    )
    args = parser.parse_args()
    curves = {run.name: [named(p, args.unprefixed) for p in read_curve(run)] for run in args.runs}
    keys = {split(k) for c in curves.values() for p in c for k in p if split(k)[1] in MEASURES}
    sets = sorted({s for s, _ in keys})
    measures = [m for m in MEASURES if any(m == k for _, k in keys)]
    levers = sorted({re.sub(r"_seed\d+$", "", name) for name in curves})
    colours = {lever: f"C{i}" for i, lever in enumerate(levers)}
    fig, axes = plt.subplots(len(sets), len(measures), figsize=(3.6 * len(measures), 3.2 * len(sets)), squeeze=False)
    for row, subset in zip(axes, sets, strict=True):
        for ax, measure in zip(row, measures, strict=True):
            key = f"{subset}/{measure}" if subset else measure
            for name, curve in curves.items():
                lever = re.sub(r"_seed\d+$", "", name)
                style = "--" if name.endswith(("_seed1", "_seed3")) else "-"
                x = [p["seconds"] / 60 if args.x == "minutes" else p["step"] for p in curve]
                ax.plot(x, [p.get(key) for p in curve], style, marker="o", ms=3, color=colours[lever], label=name)
            if "retrieval" in measure:
                ax.axhline(0.25, color="grey", ls=":", lw=1)
            if measure in GOALS:
                ax.axhline(GOALS[measure], color="grey", ls="--", lw=1)
            ax.set_xlabel(f"training minutes ({args.cores})" if args.x == "minutes" else "training steps")
            ax.set_title(f"{subset.upper()} {MEASURES[measure]}".strip(), fontsize=9)
    axes[0][0].legend(fontsize=6)
    fig.tight_layout()
    args.out.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out / f"{args.name}.png", dpi=70)
    columns = [f"{s}/{m}" if s else m for s in sets for m in measures]
    (args.out / f"{args.name}.json").write_text(json.dumps(curves, indent=1))
    for title, points in (
        ("Every reading", {name: curve for name, curve in curves.items()}),
        ("Last reading of each run", {name: curve[-1:] for name, curve in curves.items()}),
    ):
        print(f"\n{title}\n\n| run | step | minutes | " + " | ".join(columns) + " |")
        print("|---|---:|---:|" + "---:|" * len(columns))
        for name, curve in points.items():
            for p in curve:
                values = " | ".join(f"{p[k]:.3f}" if p.get(k) is not None else "" for k in columns)
                print(f"| {name} | {p['step']} | {p['seconds'] / 60:.1f} | {values} |")


if __name__ == "__main__":
    main()
