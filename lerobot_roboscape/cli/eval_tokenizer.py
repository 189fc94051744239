"""`roboscape-eval-tokenizer`: the tokenizer's report on held-out frames, per view (whole frame, object, codebook).

    roboscape-eval-tokenizer --dataset.repo_id=local/roboscape_heldout \
        --dataset.root=outputs/datasets/roboscape_heldout --tokenizer=outputs/tokenizer/pretrained_model \
        --training_dir=outputs/tokenizer --output_dir=outputs/tokenizer_report
"""

import logging

import draccus

from lerobot_roboscape.cli import one_line_errors
from lerobot_roboscape.tokenizer.report import TokenizerReportConfig, evaluate_tokenizer, markdown


@one_line_errors("roboscape-eval-tokenizer")
def main(argv: list[str] | None = None):
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    cfg = draccus.parse(TokenizerReportConfig, args=argv)
    print(markdown(evaluate_tokenizer(cfg)))
    print(f"Report in {cfg.output_dir.resolve()}: tokenizer_report.md, tokenizer_report.json, reconstruction.png")


if __name__ == "__main__":
    main()
