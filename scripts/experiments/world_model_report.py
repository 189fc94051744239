"""The world models' part of the bench report, from the reports a run wrote (the pipeline's folders under
--run-dir): the targets as rows of the bench report's (`pipeline/report.py: world_model_targets`) in
results.json, a targets table on stdout, and the figures copied beside them.

    python scripts/experiments/world_model_report.py --run-dir outputs/bench --out docs/results/world_model

The action model's fidelity from new starts of its training scenes (the run's fidelity_ind/, IND) comes first
where the run has it; its figures are copied with an `ind_` prefix.

With --agreement (a `roboscape-eval-agreement` output folder, OOD; --agreement-ind, the same IND) and
--open-loop-rewards (a reward_report.json of `roboscape-reward-report --frames=open_loop`), the rows of whether the
world model judges policies as the simulator does join the targets.

With --gpu-run-dir, the same reports of models trained on a GPU (BENCH_ON_GPU) and evaluated here join results.json
under "bench_on_gpu", and the table gains their column.

With --before (an earlier results.json of this script), the table gains its values as a column, matched by the
target's name less its figures in brackets (a tokenizer's PSNR in the name changes between runs).
"""

import argparse
import json
import re
import shutil
from pathlib import Path

from lerobot_roboscape.pipeline.layout import (
    DONE_REPORT_DIR,
    FIDELITY_DIR,
    FIDELITY_IND_DIR,
    REWARD_REPORT_DIR,
)
from lerobot_roboscape.pipeline.report.figures import world_model_figure
from lerobot_roboscape.pipeline.report.world_model_targets import agreement_targets
from lerobot_roboscape.pipeline.report.write import WorldModelReports, machine
from lerobot_roboscape.world_model.measures.fidelity import read_fidelity

FIGURES = {
    FIDELITY_DIR: ("fidelity.png", "controllability.png"),
    DONE_REPORT_DIR: ("done_curves.png",),
    REWARD_REPORT_DIR: ("reward_curves.png", "goal_grid.png"),
}
REPORTS = {
    FIDELITY_DIR: ("fidelity.md",),
    DONE_REPORT_DIR: ("done_report.md",),
    REWARD_REPORT_DIR: ("reward_report.md",),
}


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run-dir", type=Path, default=Path("outputs/bench"))
    parser.add_argument("--out", type=Path, default=Path("docs/results/world_model"))
    parser.add_argument("--gpu-run-dir", type=Path, default=None)
    parser.add_argument("--agreement", type=Path, default=None)
    parser.add_argument("--agreement-ind", type=Path, default=None)
    parser.add_argument("--open-loop-rewards", type=Path, default=None)
    parser.add_argument("--before", type=Path, default=None)
    args = parser.parse_args()
    run, out = args.run_dir, args.out
    out.mkdir(parents=True, exist_ok=True)
    targets, measured = read_run(run)
    if args.agreement_ind is not None:
        targets |= agreement_targets(json.loads((args.agreement_ind / "ladder.json").read_text()), split="ind")
    if args.agreement is not None:
        ladder = json.loads((args.agreement / "ladder.json").read_text())
        open_loop = json.loads(args.open_loop_rewards.read_text()) if args.open_loop_rewards else None
        targets |= agreement_targets(ladder, open_loop)
    results = {"machine": machine(), "targets": targets, **measured}
    gpu_targets = None
    if args.gpu_run_dir is not None:
        gpu_targets, gpu_measured = read_run(args.gpu_run_dir)
        results["bench_on_gpu"] = {"targets": gpu_targets, **gpu_measured}
    (out / "results.json").write_text(json.dumps(results, indent=2))
    for folder, names in (FIGURES | {k: FIGURES[k] + REPORTS[k] for k in REPORTS}).items():
        for name in names:
            if (run / folder / name).is_file():
                shutil.copy2(run / folder / name, out / name)
    for name in FIGURES[FIDELITY_DIR] + REPORTS[FIDELITY_DIR]:
        if (run / FIDELITY_IND_DIR / name).is_file():
            shutil.copy2(run / FIDELITY_IND_DIR / name, out / f"ind_{name}")
    world_model_figure(
        run / FIDELITY_DIR / "side_by_side.mp4",
        read_fidelity(run / FIDELITY_DIR)["prompt_frames"],
        out / "world_model_open_loop.png",
    )
    if args.before is not None:
        before = {_plain(name): t for name, t in json.loads(args.before.read_text())["targets"].items()}
        print("| target | before | measured | goal | met | detail |\n|---|---:|---:|---|:---:|---|")
        for name, t in targets.items():
            was = _value(before[_plain(name)]) if _plain(name) in before else "-"
            print(f"| {name} | {was} | {_value(t)} | {t['goal']} | {_met(t)} | {t.get('detail', '')} |")
        return
    if gpu_targets is None:
        print("| target | measured | goal | met | detail |\n|---|---:|---|:---:|---|")
        for name, t in targets.items():
            print(f"| {name} | {_value(t)} | {t['goal']} | {_met(t)} | {t.get('detail', '')} |")
        return
    print("| target | 2 cores | met | trained on the GPU | met | goal |\n|---|---:|:---:|---:|:---:|---|")
    for name, t in targets.items():
        g = gpu_targets.get(name)
        gpu = (_value(g), _met(g)) if g else ("-", "")
        print(f"| {name} | {_value(t)} | {_met(t)} | {gpu[0]} | {gpu[1]} | {t['goal']} |")


def read_run(run: Path) -> tuple[dict, dict]:
    """The targets and the measured results of the fidelity, done and reward reports under `run`."""
    reports = WorldModelReports.read(run)
    return reports.targets(), reports.results()


def _plain(name: str) -> str:
    """A target's name less a bracket with figures in it: "open-loop PSNR (dB; tokenizer 26.40)" -> "open-loop PSNR"."""
    return re.sub(r" \([^()]*\d[^()]*\)", "", name)


def _value(t: dict) -> str:
    return "-" if t["value"] is None else f"{t['value']:.3f}"


def _met(t: dict) -> str:
    return "yes" if t["met"] else "**no**"


if __name__ == "__main__":
    main()
