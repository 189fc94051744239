"""Training the image tokenizer on the camera frames of a LeRobot dataset."""

from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from accelerate.utils import set_seed
from lerobot.configs.default import DatasetConfig

from lerobot_roboscape.dataset.reader import CameraFrames, DatasetError, image_size, open_dataset
from lerobot_roboscape.perceptual import load_lpips
from lerobot_roboscape.tokenizer.configuration_tokenizer import TinyTokenizerConfig, TokenizerConfig
from lerobot_roboscape.tokenizer.modeling_tokenizer import VisualTokenizer
from lerobot_roboscape.training import TrainingConfig, fit


@dataclass
class TokenizerTrainingConfig(TrainingConfig):
    steps: int = 600
    lr: float = 1e-3


@dataclass
class TrainTokenizerConfig:
    """Args:
    dataset: the LeRobot dataset (--dataset.repo_id, --dataset.root, --dataset.episodes).
    tokenizer: architecture and losses (--tokenizer.type=tiny|paper, then any field).
    train: optimisation, logging, checkpoints and resume; batch_size counts frames (all views of each).
    output_dir: checkpoints, logs and the final model (output_dir/pretrained_model).
    num_workers: data-loading processes.
    lpips_weights: torchvision trunk weights for the perceptual loss (default: the torch hub cache).
    allow_random_lpips: train with a random LPIPS trunk when no weights are found (offline demos and tests).
    """

    dataset: DatasetConfig = field(default_factory=lambda: DatasetConfig(repo_id="local/roboscape"))
    tokenizer: TokenizerConfig = field(default_factory=TinyTokenizerConfig)
    train: TokenizerTrainingConfig = field(default_factory=TokenizerTrainingConfig)
    output_dir: Path = Path("outputs/tokenizer")
    num_workers: int = 2
    lpips_weights: Path | None = None
    allow_random_lpips: bool = False


class RandomFrameBatches:
    """Batches of random frames drawn by a per-step seed, loaded by a DataLoader's worker processes."""

    def __init__(self, frames: CameraFrames, batch_size: int, seed: int, num_workers: int):
        self.frames, self.batch_size, self.seed, self.num_workers = frames, batch_size, seed, num_workers
        self._iterator, self._next_step = None, None

    def _indices(self, start: int, process_index: int):
        for step in range(start, 2**62):
            rng = np.random.default_rng([self.seed, step, process_index])
            yield rng.integers(0, len(self.frames), self.batch_size).tolist()

    def __call__(self, step: int, process_index: int = 0) -> dict:
        if step != self._next_step:
            loader = torch.utils.data.DataLoader(
                self.frames,
                batch_sampler=self._indices(step, process_index),
                num_workers=self.num_workers,
                persistent_workers=False,
            )
            self._iterator = iter(loader)
        self._next_step = step + 1
        views = next(self._iterator)  # (B, n_cameras, 3, H, W)
        return {"images": views.flatten(0, 1)}


def train_tokenizer(cfg: TrainTokenizerConfig) -> VisualTokenizer:
    dataset = open_dataset(cfg.dataset.repo_id, cfg.dataset.root, cfg.dataset.episodes)
    size = image_size(dataset)
    if size != cfg.tokenizer.image_size:
        raise DatasetError(
            f"dataset {dataset.root} has {size}x{size} images but --tokenizer.image_size is "
            f"{cfg.tokenizer.image_size}; collect at that size or set --tokenizer.image_size={size}"
        )
    set_seed(cfg.train.seed)  # before the LPIPS trunk too, which is random when no weights are found
    lpips_metric = None
    if cfg.tokenizer.perceptual_weight > 0:
        lpips_metric = load_lpips(cfg.tokenizer.lpips_net, cfg.lpips_weights, cfg.allow_random_lpips)

    def loss_fn(model, batch):
        if lpips_metric is not None:
            lpips_metric.to(batch["images"].device)
        return model.compute_loss(batch["images"], lpips_metric)

    batches = RandomFrameBatches(CameraFrames(dataset), cfg.train.batch_size, cfg.train.seed, cfg.num_workers)
    model = VisualTokenizer(cfg.tokenizer)
    return fit(model, loss_fn, batches, cfg.train, cfg.output_dir, asdict(cfg), desc="tokenizer")
