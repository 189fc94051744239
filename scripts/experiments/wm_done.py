"""The done stage of the pipeline on one action world model trained outside a pipeline run (a `wm_levers.py` run):
the done report on the held-out OOD episodes with its threshold chosen on half the validation episodes, and the
same choice judged on the other half (IND), as `pipeline/stages.py: done_report` makes them; prints the done
targets. DATA is a run's output folder that holds its datasets (a pipeline run, or the reduced copy
`outputs/screen`); the reports go under OUT.

    python scripts/experiments/wm_done.py outputs/screen outputs/screen/bench60/bench_seed0/pretrained_model \
        --tokenizer outputs/screen/tokenizer/pretrained_model --out outputs/screen/bench60/bench_seed0/done
"""

import argparse
import json
from pathlib import Path

from lerobot.configs.default import DatasetConfig

from lerobot_roboscape.pipeline import stages
from lerobot_roboscape.pipeline.config import scale_config
from lerobot_roboscape.pipeline.data_stages import Datasets
from lerobot_roboscape.pipeline.layout import (
    DEMOS_DIR,
    DEMOS_REPO_ID,
    DONE_REPORT_DIR,
    DONE_REPORT_IND_DIR,
    HELDOUT_DIR,
    VALIDATION_DIR,
    WorldModelPaths,
)
from lerobot_roboscape.pipeline.report.world_model_targets import done_ind_targets, done_targets
from lerobot_roboscape.reward.done_readings import DoneReport
from lerobot_roboscape.reward.done_report import read_done_report


def local(data: Path, folder: str, repo_id: str | None = None) -> DatasetConfig:
    return DatasetConfig(repo_id=repo_id or f"local/{Path(folder).name}", root=str(data / folder))


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("data", type=Path, help="a run's output folder with its datasets")
    parser.add_argument("model", type=Path, help="an action world model's pretrained_model folder")
    parser.add_argument("--tokenizer", type=Path, required=True)
    parser.add_argument("--scale", default="bench", help="the scale whose report settings apply (report_episodes)")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    cfg = scale_config(args.scale, (f"--output_dir={args.out}",))
    data = Datasets(
        train=local(args.data, DEMOS_DIR, DEMOS_REPO_ID),
        heldout=local(args.data, HELDOUT_DIR),
        validation=local(args.data, VALIDATION_DIR),
        controllability=None,
        trajectory_file=Path(),
    )
    out = args.out.resolve()
    choice = stages.done_report(cfg, out, data, args.tokenizer, WorldModelPaths(args.model, args.model), {})
    targets = done_targets(DoneReport.from_json(read_done_report(out / DONE_REPORT_DIR)))
    targets |= done_ind_targets(DoneReport.from_json(read_done_report(out / DONE_REPORT_IND_DIR)))
    print(f"done: {choice.source} at threshold {choice.theta:.3f}")
    for name, t in targets.items():
        print(f"{name}: {t['value']} (goal {t['goal']}; {'met' if t['met'] else 'missed'}) {t.get('detail', '')}")
    (out / "done_targets.json").write_text(json.dumps(targets, indent=2))


if __name__ == "__main__":
    main()
