"""Training the image tokenizer on the camera frames of a LeRobot dataset."""

from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from accelerate.utils import set_seed
from lerobot.configs.default import DatasetConfig
from torchvision.transforms.v2.functional import adjust_hue

from lerobot_roboscape.dataset.reader import (
    CameraFrames,
    DatasetError,
    FrameBank,
    camera_names,
    image_size,
    open_dataset,
)
from lerobot_roboscape.dataset.segmentation import SEGMENTATION_META, has_masks
from lerobot_roboscape.metrics.perceptual import load_lpips
from lerobot_roboscape.tokenizer.configuration_tokenizer import TinyTokenizerConfig, TokenizerConfig
from lerobot_roboscape.tokenizer.modeling_tokenizer import VisualTokenizer
from lerobot_roboscape.tokenizer.report import curve_point, measure_tokenizer
from lerobot_roboscape.training.loop import TrainingConfig, fit


@dataclass
class TokenizerTrainingConfig(TrainingConfig):
    steps: int = 600
    lr: float = 1e-3


@dataclass
class TrainTokenizerConfig:
    """Args:
    dataset: the LeRobot dataset (--dataset.repo_id, --dataset.root, --dataset.episodes).
    heldout: held-out episodes measured every train.eval_freq steps (tokenizer/report.py), for the curves that
        size the run; recorded with --segmentation=true for the object measures. Optional.
    tokenizer: architecture and losses (--tokenizer.type=tiny|bench|paper, then any field).
    train: optimisation, logging, checkpoints and resume; batch_size counts frames (all views of each).
    output_dir: checkpoints, logs, held-out curve and the final model (output_dir/pretrained_model).
    frames_in_memory_gb: decode the training frames once into memory when they fit in this much (far faster on a
        CPU); larger datasets are decoded frame by frame by `num_workers` processes.
    heldout_stride: every n-th frame of each held-out episode is measured during training.
    hue_shift: rotate each training frame's hue by a random fraction of the colour circle in [-hue_shift,
        hue_shift] (0: no augmentation), so that object colours absent from the training scenes are not new to the
        tokenizer.
    num_workers: data-loading processes, when frames are not kept in memory.
    lpips_weights: torchvision trunk weights for the perceptual loss (default: the torch hub cache).
    allow_random_lpips: train with a random LPIPS trunk when no weights are found (offline demos and tests).
    """

    dataset: DatasetConfig = field(default_factory=lambda: DatasetConfig(repo_id="local/roboscape"))
    heldout: DatasetConfig | None = None
    tokenizer: TokenizerConfig = field(default_factory=TinyTokenizerConfig)
    train: TokenizerTrainingConfig = field(default_factory=TokenizerTrainingConfig)
    output_dir: Path = Path("outputs/tokenizer")
    frames_in_memory_gb: float = 8.0
    heldout_stride: int = 4
    hue_shift: float = 0.0
    num_workers: int = 2
    lpips_weights: Path | None = None
    allow_random_lpips: bool = False


def _sample(step: int, process_index: int, seed: int, n: int, batch_size: int) -> list[int]:
    """The frames of one step: a pure function of (seed, step, process), so a resumed run draws the same batches."""
    return np.random.default_rng([seed, step, process_index]).integers(0, n, batch_size).tolist()


class BankBatches:
    """Batches of random frames from a `FrameBank` in memory."""

    def __init__(self, bank: FrameBank, batch_size: int, seed: int):
        self.bank, self.batch_size, self.seed = bank, batch_size, seed

    def __call__(self, step: int, process_index: int = 0) -> dict:
        rows = _sample(step, process_index, self.seed, len(self.bank), self.batch_size)
        batch = {"images": self.bank.images[rows].flatten(0, 1).permute(0, 3, 1, 2).float() / 255}
        if self.bank.masks is not None:
            batch["masks"] = self.bank.masks[rows].flatten(0, 1)
        return batch


class StreamedBatches:
    """Batches of random frames decoded from the videos by a DataLoader's worker processes."""

    def __init__(self, frames: CameraFrames, batch_size: int, seed: int, num_workers: int):
        self.frames, self.batch_size, self.seed, self.num_workers = frames, batch_size, seed, num_workers
        self._iterator, self._next_step = None, None

    def __call__(self, step: int, process_index: int = 0) -> dict:
        if step != self._next_step:
            n, size, seed = len(self.frames), self.batch_size, self.seed
            loader = torch.utils.data.DataLoader(
                self.frames,
                batch_sampler=(_sample(s, process_index, seed, n, size) for s in range(step, 2**62)),
                num_workers=self.num_workers,
                persistent_workers=False,
            )
            self._iterator = iter(loader)
        self._next_step = step + 1
        return {k: v.flatten(0, 1) for k, v in next(self._iterator).items()}  # views as frames of their own


def shift_hue(images: torch.Tensor, shifts: torch.Tensor) -> torch.Tensor:
    """(B, 3, H, W) in [0, 1], each image's hue rotated by its fraction of the colour circle in `shifts` (B,)."""
    return torch.stack([adjust_hue(image, float(shift)) for image, shift in zip(images, shifts, strict=True)])


def with_hue(batches, hue_shift: float, seed: int):
    """`batches` with a random hue shift per frame (the same for each of its views), a function of (seed, step)."""

    def batch(step: int, process_index: int = 0) -> dict:
        out = batches(step, process_index)
        views = len(out["images"]) // batches.batch_size
        rng = np.random.default_rng([seed, step, process_index, 1])
        shifts = rng.uniform(-hue_shift, hue_shift, batches.batch_size).repeat(views)
        return out | {"hue": torch.from_numpy(shifts)}

    return batch


def train_tokenizer(cfg: TrainTokenizerConfig) -> VisualTokenizer:
    dataset = open_dataset(cfg.dataset.repo_id, cfg.dataset.root, cfg.dataset.episodes)
    size = image_size(dataset)
    if size != cfg.tokenizer.image_size:
        raise DatasetError(
            f"dataset {dataset.root} has {size}x{size} images but --tokenizer.image_size is "
            f"{cfg.tokenizer.image_size}; collect at that size or set --tokenizer.image_size={size}"
        )
    masks = cfg.tokenizer.object_weight > 0
    if masks and not has_masks(dataset.root):
        raise DatasetError(
            f"--tokenizer.object_weight={cfg.tokenizer.object_weight} needs the object's masks, and dataset "
            f"{dataset.root} has none ({SEGMENTATION_META} is missing); collect with --segmentation=true"
        )
    set_seed(cfg.train.seed)  # before the LPIPS trunk too, which is random when no weights are found
    lpips_metric = None
    if cfg.tokenizer.perceptual_weight > 0:
        lpips_metric = load_lpips(cfg.tokenizer.lpips_net, cfg.lpips_weights, cfg.allow_random_lpips)

    def loss_fn(model, batch):
        if lpips_metric is not None:
            lpips_metric.to(batch["images"].device)
        images = shift_hue(batch["images"], batch["hue"]) if "hue" in batch else batch["images"]
        return model.compute_loss(images, lpips_metric, batch.get("masks"))

    if FrameBank.nbytes(dataset) <= cfg.frames_in_memory_gb * 2**30:
        batches = BankBatches(FrameBank.load(dataset, masks=masks), cfg.train.batch_size, cfg.train.seed)
    else:
        frames = CameraFrames(dataset, masks=masks)
        batches = StreamedBatches(frames, cfg.train.batch_size, cfg.train.seed, cfg.num_workers)
    if cfg.hue_shift > 0:
        batches = with_hue(batches, cfg.hue_shift, cfg.train.seed)
    evaluate = None
    if cfg.heldout is not None:
        heldout = open_dataset(cfg.heldout.repo_id, cfg.heldout.root, cfg.heldout.episodes)
        bank = FrameBank.load(heldout, masks=has_masks(heldout.root), stride=cfg.heldout_stride)
        evaluate = lambda model: curve_point(measure_tokenizer(model, bank, camera_names(heldout)))  # noqa: E731
    model = VisualTokenizer(cfg.tokenizer)
    return fit(model, loss_fn, batches, cfg.train, cfg.output_dir, asdict(cfg), desc="tokenizer", evaluate=evaluate)
