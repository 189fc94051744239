"""The action world model's levers on a run's saved data, by held-out curves at equal CPU minutes (issue 70): today's
model (no state channel, a code per position, clean context), the robot's state as a channel, 2x2 codes per
position, corrupted context, and all three (since issue 72 also the anchor frame); each from several seeds. Two
runs go at a time, each on one core (one torch thread), so that every run gets the same CPU; each reads retrieval,
action gain, the state's error and the arm region's PSNR on IND and OOD controllability starts as it trains
(`--train.eval_freq`). A run's budget is wall clock, its readings included; the curves' minutes are its training
alone. Then `wm_curves.py` draws them.

The text model's runs (`text`) read its goals instead (`--heldout_goals`): how often its done crosses `--theta` within
the family's horizon from IND starts (the validation collection: new starts of the training scenes) and OOD ones (the
held-out scenes), and whether its goal is nearer the real success than the start.

    python scripts/experiments/wm_levers.py outputs/screen --out outputs/screen/levers --minutes 10
    python scripts/experiments/wm_curves.py outputs/screen/levers/* --out docs/results/world_model/levers70
    python scripts/experiments/wm_levers.py outputs/bench --out outputs/bench/text70 --runs text_seed0 --minutes 40 \
        --parallel 1 --threads 2 --steps_per_minute 150 150 --theta 0.996
"""

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

from lerobot.configs.default import DatasetConfig

from lerobot_roboscape.dataset.reader import open_dataset
from lerobot_roboscape.pipeline.layout import (
    CONTROL_DIR,
    CONTROL_IND_DIR,
    DEMOS_DIR,
    DEMOS_REPO_ID,
    EXPLORE_DIR,
    EXPLORE_REPO_ID,
    HELDOUT_DIR,
    TOKEN_CACHE_DIR,
    TOKENIZER_DIR,
    VALIDATION_DIR,
)
from lerobot_roboscape.tokenizer.modeling_tokenizer import VisualTokenizer
from lerobot_roboscape.training.checkpoints import FINAL
from lerobot_roboscape.world_model.configuration_world_model import WorldModelConfig
from lerobot_roboscape.world_model.goals import read_goal_starts, save_goal_starts
from lerobot_roboscape.world_model.measures.controllability import read_control_set, save_control_starts, spread
from lerobot_roboscape.world_model.train import prepare_token_cache

# Each lever alone against today's model, then all of them; --wm fields of the bench preset (which now corrupts its
# context, so the others turn that off).
OFF = {"corrupt_max": "0"}
LEVERS = {
    "today": {"state": "false", **OFF},
    "state": OFF,
    "patch2": {"state": "false", "patch": "2", **OFF},
    "corrupt": {"state": "false", "corrupt_max": "0.2"},
    "all": {"patch": "2", "corrupt_max": "0.2"},  # the bench preset as it stands (its patch named for the pace below)
    "bench": {"patch": "2", **OFF},  # the bench preset before corruption (corrupt70's reference)
    # the bench preset reading the episode's first frame in every frame (issue 72: 100-step rollouts drifted);
    # read it with a --horizon past the window (24 control steps), where the drift is
    "anchor": {"patch": "2", "corrupt_max": "0.2", "anchor": "true"},
    "anchor_held": {"patch": "2", "corrupt_max": "0.2", "corrupt_held": "true", "anchor": "true"},  # repair from it
    "wide": {"patch": "2", "d_model": "192", **OFF},  # 1.5x wider: give its own pace (--steps_per_minute)
    "text": {"patch": "2", "control": "text", **OFF},  # the bench preset's text model, read on its goals
}


def held_out_sets(run: Path, out: Path, text: bool, frame_skip: int, horizon: int, keep: int) -> list[Path]:
    """The IND and OOD sets read once for every run, at most `keep` starts of each, spread over the set: the
    controllability sets (ind.safetensors, ood.safetensors), or the text model's goal sets (ind_goals..., ...)."""
    tokenizer = VisualTokenizer.from_pretrained(run / TOKENIZER_DIR / FINAL).eval()
    folders = (
        (("ind_goals", VALIDATION_DIR), ("ood_goals", HELDOUT_DIR))
        if text
        else (
            ("ind", CONTROL_IND_DIR),
            ("ood", CONTROL_DIR),
        )
    )
    paths = []
    for name, folder in folders:
        path = out / f"{name}.safetensors"
        if not path.is_file():
            dataset = open_dataset(f"local/{Path(folder).name}", run / folder)
            if text:
                save_goal_starts(read_goal_starts(dataset, tokenizer, keep), path)
            else:
                starts = read_control_set(dataset, tokenizer, frame_skip, horizon, "cpu")
                save_control_starts(spread(starts, keep), path, frame_skip)
        paths.append(path)
    return paths


def command(run: Path, folder: Path, lever: dict, seed: int, minutes: float, eval_freq: int, sets: list[Path], theta):
    wm = {"type": "bench", "control": "action", **lever}
    if wm["control"] == "text":  # the demonstrations alone (its successful optimal episodes); read on its goals
        data = [f"--heldout_goals=[{','.join(str(p) for p in sets)}]", f"--heldout_theta={theta}"]
    else:
        data = [
            f"--exploration.repo_id={EXPLORE_REPO_ID}",
            f"--exploration.root={run / EXPLORE_DIR}",
            "--exploration_share=0.25",
            f"--heldout_starts=[{','.join(str(p) for p in sets)}]",
            "--done_tuning_steps=0",
        ]
    return [
        sys.executable,
        "-m",
        "lerobot_roboscape.cli.train_wm",
        f"--dataset.repo_id={DEMOS_REPO_ID}",
        f"--dataset.root={run / DEMOS_DIR}",
        *data,
        f"--tokenizer={run / TOKENIZER_DIR / FINAL}",
        f"--cache_dir={run / TOKEN_CACHE_DIR}",
        f"--output_dir={folder}",
        *(f"--wm.{k}={v}" for k, v in wm.items()),
        "--train.steps=100000",  # the time budget ends the run
        f"--train.time_budget_s={60 * minutes:.0f}",
        f"--train.eval_freq={eval_freq}",
        "--train.batch_size=4",
        f"--train.seed={seed}",
        "--train.save_freq=100000",
    ]


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path, help="a roboscape-demo output_dir with its data and tokenizer")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--levers", nargs="+", default=list(LEVERS), choices=list(LEVERS))
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--minutes", type=float, default=10.0, help="wall minutes per run, evaluations included")
    parser.add_argument("--evals", type=int, default=5, help="held-out readings per run, about")
    parser.add_argument("--steps_per_minute", type=float, nargs=2, default=(30.0, 75.0), metavar=("CODE", "PATCH2"))
    parser.add_argument("--parallel", type=int, default=2)
    parser.add_argument("--threads", type=int, default=1, help="torch threads per run")
    parser.add_argument("--runs", nargs="+", help="<lever>_seed<n> in this order, instead of every lever and seed")
    parser.add_argument("--horizon", type=int, default=16)
    parser.add_argument("--starts", type=int, default=16, help="starts per held-out set (IND, OOD), at most")
    parser.add_argument("--theta", type=float, default=0.9, help="the text model's goals: the env's done threshold")
    args = parser.parse_args()
    run, out = args.run.resolve(), args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    frame_skip = WorldModelConfig.get_choice_class("bench")().frame_skip
    tokenizer = str(run / TOKENIZER_DIR / FINAL)
    runs = [(name, seed) for seed in args.seeds for name in args.levers]
    if args.runs:
        runs = [(run.rsplit("_seed", 1)[0], int(run.rsplit("_seed", 1)[1])) for run in args.runs]
    caches = [(DEMOS_REPO_ID, DEMOS_DIR)]
    if any(LEVERS[name].get("control") != "text" for name, _ in runs):  # the text model reads no exploration
        caches.append((EXPLORE_REPO_ID, EXPLORE_DIR))
    for repo_id, folder in caches:  # built once, not raced
        prepare_token_cache(DatasetConfig(repo_id=repo_id, root=str(run / folder)), tokenizer, run / TOKEN_CACHE_DIR)
    jobs = []
    for name, seed in runs:
        lever = LEVERS[name]
        pace = args.steps_per_minute[1] if lever.get("patch") == "2" else args.steps_per_minute[0]
        eval_freq = max(1, round(pace * args.minutes / args.evals))
        folder = out / f"{name}_seed{seed}"
        if (folder / FINAL / "model.safetensors").is_file():
            continue
        sets = held_out_sets(run, out, lever.get("control") == "text", frame_skip, args.horizon, args.starts)
        jobs.append((folder, command(run, folder, lever, seed, args.minutes, eval_freq, sets, args.theta)))
    env = {**os.environ, "OMP_NUM_THREADS": str(args.threads), "MKL_NUM_THREADS": str(args.threads)}
    running: list[tuple[Path, subprocess.Popen]] = []
    while jobs or running:
        while jobs and len(running) < args.parallel:
            folder, cmd = jobs.pop(0)
            folder.mkdir(parents=True, exist_ok=True)
            log = open(folder.with_suffix(".log"), "w")  # noqa: SIM115  (closed with the process)
            print(f"start {folder.name}", flush=True)
            running.append((folder, subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT)))
        time.sleep(5)
        for item in [r for r in running if r[1].poll() is not None]:
            running.remove(item)
            print(f"{item[0].name}: exit {item[1].returncode}", flush=True)


if __name__ == "__main__":
    main()
