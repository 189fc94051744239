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
from lerobot_roboscape.world_model.fidelity import FidelityConfig, evaluate_fidelity


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
    for name, regions in report.get("controllability", {}).items():
        print(f"retrieval ({name}): " + ", ".join(f"{r} {v['retrieval']:.3f}" for r, v in regions.items()))
    print(f"Report in {cfg.output_dir.resolve()}: fidelity.md, fidelity.json, fidelity.png, side_by_side.mp4")


if __name__ == "__main__":
    main()
