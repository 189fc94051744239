"""The text world model's held-out curve on a run's saved data (issue 70): how often its done crosses theta within
the family's horizon from held-out starts, and whether its goal is nearer the real success than the start is, read
along training against CPU minutes (`--heldout_goals` of `roboscape-train-wm`), IND (the validation collection: new
starts of the training scenes) and OOD (the held-out scenes). Each run trains alone on every core, as the pipeline
trains it; its budget is wall clock, its readings included. Then `wm_curves.py` draws the curves.

    python scripts/experiments/text_wm_curve.py outputs/bench --out outputs/bench/text70 --minutes 40 --theta 0.996
    python scripts/experiments/wm_curves.py outputs/bench/text70/seed* --out docs/results/world_model/text70 \
        --cores "two cores"
"""

import argparse
import subprocess
import sys
from pathlib import Path

from lerobot.configs.default import DatasetConfig

from lerobot_roboscape.dataset.reader import open_dataset
from lerobot_roboscape.pipeline.layout import (
    DEMOS_DIR,
    DEMOS_REPO_ID,
    HELDOUT_DIR,
    TOKEN_CACHE_DIR,
    TOKENIZER_DIR,
    VALIDATION_DIR,
)
from lerobot_roboscape.tokenizer.modeling_tokenizer import VisualTokenizer
from lerobot_roboscape.training.checkpoints import FINAL
from lerobot_roboscape.world_model.goals import read_goal_starts, save_goal_starts
from lerobot_roboscape.world_model.train import prepare_token_cache


def goal_sets(run: Path, out: Path, keep: int) -> list[Path]:
    """The IND and OOD goal sets read once for every run (ind.safetensors, ood.safetensors), `keep` starts each."""
    tokenizer = VisualTokenizer.from_pretrained(run / TOKENIZER_DIR / FINAL).eval()
    paths = []
    for name, folder in (("ind", VALIDATION_DIR), ("ood", HELDOUT_DIR)):
        path = out / f"{name}.safetensors"
        if not path.is_file():
            dataset = open_dataset(f"local/{Path(folder).name}", run / folder)
            save_goal_starts(read_goal_starts(dataset, tokenizer, keep), path)
        paths.append(path)
    return paths


def command(run: Path, folder: Path, seed: int, minutes: float, eval_freq: int, sets: list[Path], theta: float):
    return [
        sys.executable,
        "-m",
        "lerobot_roboscape.cli.train_wm",
        f"--dataset.repo_id={DEMOS_REPO_ID}",
        f"--dataset.root={run / DEMOS_DIR}",
        f"--tokenizer={run / TOKENIZER_DIR / FINAL}",
        f"--cache_dir={run / TOKEN_CACHE_DIR}",
        f"--output_dir={folder}",
        "--wm.type=bench",
        "--wm.control=text",
        "--train.steps=100000",  # the time budget ends the run
        f"--train.time_budget_s={60 * minutes:.0f}",
        f"--train.eval_freq={eval_freq}",
        "--train.batch_size=4",
        f"--train.seed={seed}",
        "--train.save_freq=100000",
        f"--heldout_goals=[{','.join(str(p) for p in sets)}]",
        f"--heldout_theta={theta}",
    ]


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path, help="a roboscape-demo output_dir with its data and tokenizer")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--minutes", type=float, default=40.0, help="wall minutes per run, readings included")
    parser.add_argument("--evals", type=int, default=6, help="held-out readings per run, about")
    parser.add_argument("--steps_per_minute", type=float, default=150.0, help="the text model's pace, to space them")
    parser.add_argument("--starts", type=int, default=32, help="starts per goal set (IND, OOD), at most")
    parser.add_argument("--theta", type=float, default=0.9, help="the env's done threshold (--env.theta)")
    args = parser.parse_args()
    run, out = args.run.resolve(), args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    tokenizer, demos = str(run / TOKENIZER_DIR / FINAL), DatasetConfig(repo_id=DEMOS_REPO_ID, root=str(run / DEMOS_DIR))
    prepare_token_cache(demos, tokenizer, run / TOKEN_CACHE_DIR)  # built before the clock starts
    sets = goal_sets(run, out, args.starts)
    eval_freq = max(1, round(args.steps_per_minute * args.minutes / args.evals))
    for seed in args.seeds:
        folder = out / f"seed{seed}"
        if (folder / FINAL / "model.safetensors").is_file():
            continue
        folder.mkdir(parents=True, exist_ok=True)
        print(f"start {folder.name}", flush=True)
        with open(folder.with_suffix(".log"), "w") as log:
            cmd = command(run, folder, seed, args.minutes, eval_freq, sets, args.theta)
            code = subprocess.run(cmd, stdout=log, stderr=subprocess.STDOUT).returncode
        print(f"{folder.name}: exit {code}", flush=True)


if __name__ == "__main__":
    main()
