"""Tokenizer loss and size ablation at equal steps: each variant trains on the same frames and batches, measured on
the held-out OOD frames (tokenizer/report.py) every few steps; the table gives each variant's final measures per
view and its wall time. Variants run side by side, one process and one torch thread each (a 2-core machine runs
two at a time, as fast per variant as one alone with two threads).

    python scripts/experiments/tokenizer_ablation.py --train outputs/bench/datasets/roboscape_demos \
        --heldout outputs/bench/datasets/roboscape_heldout --steps 1500 --out outputs/tokenizer_ablation \
        --variants l1 object_w20 entropy_0.02

A variant is a name from VARIANTS; a finished variant (its report exists) is not trained again.
"""

import argparse
import json
import multiprocessing as mp
import time
from dataclasses import replace
from pathlib import Path

from lerobot.configs.default import DatasetConfig

from lerobot_roboscape.tokenizer.report import REPORT_JSON, read_tokenizer_report

# The baseline: the bench preset's losses before this ablation (L1 and LFQ's losses only, entropy weight 0.1).
BASELINE = {"object_weight": 0.0, "entropy_weight": 0.1}
# Changes from the baseline, by variant name (the bench preset's architecture throughout unless named).
VARIANTS = {
    "l1": {},
    "object_w5": {"object_weight": 5.0},
    "object_w20": {"object_weight": 20.0},
    "object_w50": {"object_weight": 50.0},
    "entropy_0.02": {"entropy_weight": 0.02},
    "bits_12": {"codebook_bits": 12},
    "object_w20_entropy_0.02": {"object_weight": 20.0, "entropy_weight": 0.02},
    "object_w50_entropy_0.02": {"object_weight": 50.0, "entropy_weight": 0.02},
    "object_w20_entropy_0.005": {"object_weight": 20.0, "entropy_weight": 0.005},
    "object_w20_wide": {"object_weight": 20.0, "base_channels": 32},
    "object_w100_entropy_0.02": {"object_weight": 100.0, "entropy_weight": 0.02},
    "object_w50_entropy_0.02_hue": {"object_weight": 50.0, "entropy_weight": 0.02, "hue_shift": 0.5},
    # the bench preset trained under bf16 autocast (1.7x faster a step on a CPU with AVX512-BF16)
    "object_w50_entropy_0.02_bf16": {"object_weight": 50.0, "entropy_weight": 0.02, "mixed_precision": "bf16"},
}
TRAINING_OPTIONS = ("hue_shift",)  # of TrainTokenizerConfig, not of the tokenizer
OPTIMISATION_OPTIONS = ("mixed_precision",)  # of its TokenizerTrainingConfig


def run_variant(name: str, args) -> dict:
    import torch

    torch.set_num_threads(args.threads)
    from lerobot_roboscape.tokenizer.configuration_tokenizer import BenchTokenizerConfig
    from lerobot_roboscape.tokenizer.report import TokenizerReportConfig, evaluate_tokenizer
    from lerobot_roboscape.tokenizer.train import TokenizerTrainingConfig, TrainTokenizerConfig, train_tokenizer

    changes = BASELINE | VARIANTS[name]
    training = {k: changes.pop(k) for k in TRAINING_OPTIONS if k in changes}
    optimisation = {k: changes.pop(k) for k in OPTIMISATION_OPTIONS if k in changes}
    folder = Path(args.out) / name
    if (folder / "report" / REPORT_JSON).exists():
        return read_tokenizer_report(folder / "report")
    train = TrainTokenizerConfig(
        dataset=DatasetConfig(repo_id="local/train", root=args.train),
        heldout=DatasetConfig(repo_id="local/heldout", root=args.heldout),
        tokenizer=replace(BenchTokenizerConfig(), **changes),
        train=TokenizerTrainingConfig(
            steps=args.steps,
            batch_size=args.batch_size,
            lr=args.lr,
            save_freq=args.steps,
            eval_freq=args.eval_freq,
            resume=(folder / "train" / "checkpoints").exists(),
            **optimisation,
        ),
        output_dir=folder / "train",
        heldout_stride=args.heldout_stride,
        **training,
    )
    began = time.time()
    train_tokenizer(train)
    seconds = time.time() - began
    report = evaluate_tokenizer(
        TokenizerReportConfig(
            dataset=train.heldout,
            tokenizer=str(folder / "train" / "pretrained_model"),
            output_dir=folder / "report",
            training_dir=folder / "train",
            device="cpu",
        )
    )
    report["train_seconds"] = seconds
    (folder / "report" / REPORT_JSON).write_text(json.dumps(report, indent=2))
    return report


def table(reports: dict[str, dict]) -> str:
    fmt = lambda v, f="{:.2f}": "-" if v is None else f.format(v)  # noqa: E731
    lines = [
        "| variant | change from the L1 baseline | view | PSNR (dB) | object PSNR (dB) | object survives | codes used "
        "| perplexity | train min |",
        "|---|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    for name, report in reports.items():
        for view, m in report["views"].items():
            lines.append(
                f"| {name} | {VARIANTS[name] or BASELINE} | {view} | {fmt(m['psnr'])} | "
                f"{fmt(m['object_psnr'])} | "
                f"{fmt(m['object_survival'], '{:.1%}')} | {m['codebook']['share_used']:.1%} | "
                f"{m['codebook']['perplexity']:.0f} | {report.get('train_seconds', 0) / 60:.1f} |"
            )
    return "\n".join(lines) + "\n"


def curves_figure(reports: dict[str, dict], path: Path) -> None:
    """Held-out curves of every variant: a row per view, a column per measure."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    views = list(next(iter(reports.values()))["views"])
    measures = ("psnr", "object_psnr", "object_survival")
    fig, axes = plt.subplots(len(views), len(measures), figsize=(12, 3 * len(views)), squeeze=False)
    for row, view in zip(axes, views, strict=True):
        for ax, measure in zip(row, measures, strict=True):
            for name, report in reports.items():
                curve = report["curve"]
                ax.plot([p["step"] for p in curve], [p[f"{view}/{measure}"] for p in curve], "-o", ms=3, label=name)
            ax.set_title(f"{view}: held-out {measure.replace('_', ' ')}")
            ax.set_xlabel("training step")
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--train", required=True)
    parser.add_argument("--heldout", required=True)
    parser.add_argument("--out", default="outputs/tokenizer_ablation")
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    parser.add_argument("--steps", type=int, default=1500)
    parser.add_argument("--batch-size", type=int, default=8)
    parser.add_argument("--lr", type=float, default=1e-3)
    parser.add_argument("--eval-freq", type=int, default=250)
    parser.add_argument("--heldout-stride", type=int, default=4)
    parser.add_argument("--parallel", type=int, default=2)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    with mp.get_context("spawn").Pool(args.parallel) as pool:
        reports = dict(
            zip(args.variants, pool.starmap(run_variant, [(v, args) for v in args.variants], chunksize=1), strict=True)
        )
    text = table(reports)
    (Path(args.out) / "ablation.md").write_text(text)
    curves_figure(reports, Path(args.out) / "ablation_curves.png")
    print(text)


if __name__ == "__main__":
    main()
