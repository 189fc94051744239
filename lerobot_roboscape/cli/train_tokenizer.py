"""`roboscape-train-tokenizer`: train the image tokenizer on a LeRobot dataset.

    roboscape-train-tokenizer --dataset.repo_id=local/roboscape --dataset.root=outputs/datasets/roboscape \
        --output_dir=outputs/tokenizer [--tokenizer.type=paper] [--train.steps=2000] [--train.resume=true]
"""

import logging

import draccus

from lerobot_roboscape.cli import one_line_errors
from lerobot_roboscape.tokenizer.train import TrainTokenizerConfig, train_tokenizer
from lerobot_roboscape.training.checkpoints import FINAL


@one_line_errors("roboscape-train-tokenizer")
def main(argv: list[str] | None = None):
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    cfg = draccus.parse(TrainTokenizerConfig, args=argv)
    train_tokenizer(cfg)
    print(f"Tokenizer saved to {(cfg.output_dir / FINAL).resolve()}")


if __name__ == "__main__":
    main()
