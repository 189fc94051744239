"""Held-out curves of action world-model runs side by side: retrieval (whole frame, object) and action gain on the
controllability set against training minutes, from each run's heldout_curve.jsonl (`roboscape-train-wm
--heldout_control...`). Writes OUT/wm_curves.png and prints a markdown table of each run at every point.

    python scripts/experiments/wm_curves.py outputs/wm37/wm_share0 outputs/wm37/wm_share0.5 \
        --out docs/results/world_model
"""

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from lerobot_roboscape.training.loop import read_curve  # noqa: E402

MEASURES = {
    "retrieval_whole_frame": "retrieval, whole frame (K = 4)",
    "retrieval_object": "retrieval, object region",
    "action_gain_db": "action gain (dB)",
    "likelihood_retrieval": "retrieval from the likelihood",
}


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", type=Path, nargs="+", help="output_dir of each roboscape-train-wm run")
    parser.add_argument("--out", type=Path, default=Path("docs/results/world_model"))
    parser.add_argument("--name", default="wm_curves")
    parser.add_argument("--x", choices=("minutes", "steps"), default="minutes", help="steps: for runs not timed alone")
    args = parser.parse_args()
    curves = {run.name: read_curve(run) for run in args.runs}
    measures = {k: v for k, v in MEASURES.items() if any(k in p for c in curves.values() for p in c)}
    fig, axes = plt.subplots(1, len(measures), figsize=(5 * len(measures), 3.6))
    for ax, (key, label) in zip(axes, measures.items(), strict=True):
        for name, curve in curves.items():
            x = [p["seconds"] / 60 if args.x == "minutes" else p["step"] for p in curve]
            ax.plot(x, [p.get(key) for p in curve], marker="o", ms=3, label=name)
        if "retrieval" in key:
            ax.axhline(0.25, color="grey", ls=":", lw=1, label="chance")
            ax.axhline(0.9, color="grey", ls="--", lw=1, label="goal")
        else:
            ax.axhline(3.0, color="grey", ls="--", lw=1, label="goal")
        ax.set_xlabel("training minutes (2 CPU cores)" if args.x == "minutes" else "training steps")
        ax.set_title(label)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    args.out.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out / f"{args.name}.png", dpi=70)
    print("| run | step | minutes | " + " | ".join(measures) + " |")
    print("|---|---:|---:|" + "---:|" * len(measures))
    for name, curve in curves.items():
        for p in curve:
            values = " | ".join(f"{p[k]:.3f}" if p.get(k) is not None else "" for k in measures)
            print(f"| {name} | {p['step']} | {p['seconds'] / 60:.1f} | {values} |")


if __name__ == "__main__":
    main()
