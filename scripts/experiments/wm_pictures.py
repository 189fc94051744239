"""The controllability picture of trained action world models (each sequence's real future beside its rollout) on
the first starts of a run's IND controllability set, one picture per model: what the issue-70 report shows before
and after. Writes OUT/controllability_<name>.png, where <name> is the model's run folder.

    python scripts/experiments/wm_pictures.py outputs/screen outputs/screen/levers20/today_seed0 \
        outputs/screen/bench60/bench_seed0 --out docs/results/world_model/levers70
    python scripts/experiments/wm_pictures.py outputs/bench outputs/bench/anchor72/all_seed0 \
        outputs/bench/anchor72/anchor_held_seed0 --out docs/results/world_model/anchor72 --starts 2 --horizon 48
"""

import argparse
import shutil
import tempfile
from pathlib import Path

from lerobot.configs.default import DatasetConfig

from lerobot_roboscape.pipeline.layout import CONTROL_IND_DIR, TOKENIZER_DIR
from lerobot_roboscape.training.checkpoints import FINAL
from lerobot_roboscape.world_model.measures.controllability import ControllabilityReportConfig, evaluate_controllability


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path, help="a roboscape-demo output_dir with its controllability sets")
    parser.add_argument("models", type=Path, nargs="+", help="roboscape-train-wm output_dirs")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--starts", type=int, default=4, help="starts drawn (K = 4 sequences each)")
    parser.add_argument("--horizon", type=int, default=16, help="control steps rolled out (48: twice the window)")
    args = parser.parse_args()
    control = args.run / CONTROL_IND_DIR
    args.out.mkdir(parents=True, exist_ok=True)
    for model in args.models:
        with tempfile.TemporaryDirectory() as tmp:
            cfg = ControllabilityReportConfig(
                dataset=DatasetConfig(
                    repo_id=f"local/{control.name}", root=str(control), episodes=list(range(4 * args.starts))
                ),
                tokenizer=str(args.run / TOKENIZER_DIR / FINAL),
                world_model=str(model / FINAL),
                output_dir=Path(tmp),
                horizon=args.horizon,
                picture_starts=args.starts,
                device="cpu",
            )
            summary = evaluate_controllability(cfg)["summary"]
            shutil.copy2(Path(tmp) / "controllability.png", args.out / f"controllability_{model.name}.png")
        print(model.name, {k: round(v, 3) for k, v in summary.items() if isinstance(v, float)}, flush=True)


if __name__ == "__main__":
    main()
