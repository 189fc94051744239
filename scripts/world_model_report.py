"""The world models' part of the bench report, from the reports a run wrote (the pipeline's folders under
--run-dir): the targets as rows of the bench report's (`pipeline/report.py: world_model_targets`) in
results.json, a targets table on stdout, and the figures copied beside them.

    python scripts/world_model_report.py --run-dir outputs/bench --out docs/results/world_model
"""

import argparse
import json
import shutil
from pathlib import Path

from lerobot_roboscape.pipeline.report import machine, world_model_figure, world_model_results, world_model_targets
from lerobot_roboscape.pipeline.stages import DONE_REPORT_DIR, FIDELITY_DIR, REWARD_REPORT_DIR, world_model_dir
from lerobot_roboscape.training import read_curve

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
    args = parser.parse_args()
    run, out = args.run_dir, args.out
    out.mkdir(parents=True, exist_ok=True)
    fidelity = json.loads((run / FIDELITY_DIR / "fidelity.json").read_text())
    done = json.loads((run / DONE_REPORT_DIR / "done_report.json").read_text())
    rewards = json.loads((run / REWARD_REPORT_DIR / "reward_report.json").read_text())
    targets = world_model_targets(fidelity, done, rewards, read_curve(run / world_model_dir("action")))
    results = {"machine": machine(), "targets": targets, **world_model_results(fidelity, done, rewards)}
    (out / "results.json").write_text(json.dumps(results, indent=2))
    for folder, names in (FIGURES | {k: FIGURES[k] + REPORTS[k] for k in REPORTS}).items():
        for name in names:
            if (run / folder / name).is_file():
                shutil.copy2(run / folder / name, out / name)
    world_model_figure(
        run / FIDELITY_DIR / "side_by_side.mp4", fidelity["prompt_frames"], out / "world_model_open_loop.png"
    )
    print("| target | measured | goal | met | detail |\n|---|---:|---|:---:|---|")
    for name, t in targets.items():
        value = "-" if t["value"] is None else f"{t['value']:.3f}"
        print(f"| {name} | {value} | {t['goal']} | {'yes' if t['met'] else '**no**'} | {t.get('detail', '')} |")


if __name__ == "__main__":
    main()
