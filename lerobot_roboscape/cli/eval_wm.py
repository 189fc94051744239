"""`roboscape-eval-wm`: fidelity report of the action world model on held-out episodes.

    roboscape-eval-wm --dataset.repo_id=local/roboscape --dataset.root=outputs/datasets/roboscape_heldout \
        --tokenizer=outputs/tokenizer/pretrained_model --world_model=outputs/wm_action/pretrained_model \
        --output_dir=outputs/fidelity \
        --controllability.repo_id=local/roboscape_controllability \
        --controllability.root=outputs/datasets/roboscape_controllability   # optional: does it follow its actions?
"""

import logging

import draccus

from lerobot_roboscape.cli import one_line_errors
from lerobot_roboscape.world_model.measures.fidelity import FidelityConfig, evaluate_fidelity


@one_line_errors("roboscape-eval-wm")
def main(argv: list[str] | None = None):
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    cfg = draccus.parse(FidelityConfig, args=argv)
    report = evaluate_fidelity(cfg)
    mean = report["mean"]
    print(
        f"PSNR {mean['prediction_psnr']:.2f} (tokenizer {mean['reconstruction_psnr']:.2f}), "
        f"SSIM {mean['prediction_ssim']:.3f}, LPIPS {mean['prediction_lpips']:.3f}"
    )
    for reading in ("controllability", "controllability_long"):
        if reading not in report:
            continue
        horizon = cfg.horizon if reading == "controllability" else cfg.long_horizon
        summary = report[reading]
        for name in ("world_model", "ignoring_actions"):
            retrieval = ", ".join(f"{r} {v['retrieval']:.3f}" for r, v in summary[name].items())
            print(f"retrieval over {horizon} control steps ({name}): {retrieval}")
        print(f"action gain over {horizon} control steps: {summary['action_gain_db']:.2f} dB")
    print(f"Report in {cfg.output_dir.resolve()}: fidelity.md, fidelity.json, fidelity.png, side_by_side.mp4")


if __name__ == "__main__":
    main()
