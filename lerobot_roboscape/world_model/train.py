"""Training a world model (action- or text-conditioned) on a pre-tokenised LeRobot dataset."""

import logging
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from accelerate.utils import set_seed
from lerobot.configs.default import DatasetConfig
from lerobot.utils.constants import ACTION

from lerobot_roboscape.dataset.reader import open_dataset
from lerobot_roboscape.tokenizer.modeling_tokenizer import VisualTokenizer
from lerobot_roboscape.tokenizer.token_cache import (
    TokenCache,
    dataset_fingerprint,
    load_or_build_token_cache,
    open_token_cache,
    tokenizer_fingerprint,
)
from lerobot_roboscape.training import TrainingConfig, fit, resolve_device
from lerobot_roboscape.world_model.clips import ClipSampler, select_episodes
from lerobot_roboscape.world_model.configuration_world_model import TinyWorldModelConfig, WorldModelConfig
from lerobot_roboscape.world_model.modeling_world_model import STWorldModel

logger = logging.getLogger(__name__)


@dataclass
class WorldModelTrainingConfig(TrainingConfig):
    steps: int = 800
    batch_size: int = 8
    lr: float = 1e-3


@dataclass
class TrainWorldModelConfig:
    """Args:
    dataset: the LeRobot dataset; --dataset.episodes picks the training episodes (default: all).
    tokenizer: trained tokenizer, a local directory or a Hub repo id.
    wm: the world model (--wm.type=tiny|paper, --wm.control=action|text, then any field). Its frame layout
        (cameras, grid side, vocabulary) and action width are taken from the token cache.
    train: optimisation, logging, checkpoints and resume.
    output_dir: checkpoints, logs and the final model (output_dir/pretrained_model).
    cache_dir: where token caches are built and found (one per dataset and tokenizer).
    token_cache: use this existing cache; it must match the dataset and tokenizer.
    only_optimal: train on optimal episodes only (default: yes for the text model, no for the action model).
    only_successful: train on successful episodes only (default: yes for the text model, no for the action model).
    device: where to tokenize ("auto": cuda when available).
    """

    dataset: DatasetConfig = field(default_factory=lambda: DatasetConfig(repo_id="local/roboscape"))
    tokenizer: str = "outputs/tokenizer/pretrained_model"
    wm: WorldModelConfig = field(default_factory=TinyWorldModelConfig)
    train: WorldModelTrainingConfig = field(default_factory=WorldModelTrainingConfig)
    output_dir: Path = Path("outputs/world_model")
    cache_dir: Path = Path("outputs/token_cache")
    token_cache: Path | None = None
    only_optimal: bool | None = None
    only_successful: bool | None = None
    device: str = "auto"


def prepare_token_cache(
    dataset_cfg: DatasetConfig,
    tokenizer_path: str,
    cache_dir: Path,
    token_cache: Path | None = None,
    device: str = "auto",
) -> tuple[TokenCache, dict]:
    """The token cache of every episode of the dataset under this tokenizer, built on first use, and the dataset's
    action statistics (LeRobot's dataset.meta.stats["action"])."""
    dataset = open_dataset(dataset_cfg.repo_id, dataset_cfg.root)  # the cache covers all episodes
    stats = dataset.meta.stats[ACTION]
    tokenizer = VisualTokenizer.from_pretrained(tokenizer_path)
    if token_cache is not None:
        cache = open_token_cache(token_cache, dataset_fingerprint(dataset.root), tokenizer_fingerprint(tokenizer))
    else:
        cache = load_or_build_token_cache(dataset, tokenizer, cache_dir, device=resolve_device(device))
    return cache, stats


def fit_config_to_cache(wm: WorldModelConfig, cache: TokenCache, action_stats: dict) -> WorldModelConfig:
    """Frame layout, action width and action statistics come from the data; say so when the layout differs from
    the preset."""
    for name, value in (
        ("n_cameras", len(cache.cameras)),
        ("tokens_per_side", cache.tokens_per_side),
        ("vocab_size", cache.vocab_size),
        ("action_dim", cache.action_dim),
    ):
        if getattr(wm, name) != value:
            logger.info("wm.%s = %s (from the token cache; the preset had %s)", name, value, getattr(wm, name))
            setattr(wm, name, value)
    wm.action_mean = np.asarray(action_stats["mean"], dtype=np.float64).reshape(-1).tolist()
    wm.action_std = np.asarray(action_stats["std"], dtype=np.float64).reshape(-1).tolist()
    wm.__post_init__()  # the statistics must fit the action layout
    return wm


def train_world_model(cfg: TrainWorldModelConfig) -> STWorldModel:
    cache, action_stats = prepare_token_cache(cfg.dataset, cfg.tokenizer, cfg.cache_dir, cfg.token_cache, cfg.device)
    text = cfg.wm.control == "text"
    episodes = select_episodes(
        cache,
        cfg.dataset.episodes,
        only_optimal=text if cfg.only_optimal is None else cfg.only_optimal,
        only_successful=text if cfg.only_successful is None else cfg.only_successful,
    )
    logger.info(
        "training the %s world model on %d episodes (%d frames) of %s",
        cfg.wm.control,
        len(episodes),
        sum(row["length"] for row in episodes),
        cache.root,
    )
    set_seed(cfg.train.seed)  # the initial weights too, so a run is reproducible
    model = STWorldModel(fit_config_to_cache(cfg.wm, cache, action_stats))
    batches = ClipSampler(
        cache, episodes, cfg.wm.window, cfg.train.batch_size, cfg.train.seed, frame_skip=cfg.wm.frame_skip
    )
    run_config = {**asdict(cfg), "token_cache": str(cache.root)}
    return fit(
        model,
        lambda m, batch: m(batch),
        batches,
        cfg.train,
        cfg.output_dir,
        run_config,
        desc=f"{cfg.wm.control} world model",
    )
