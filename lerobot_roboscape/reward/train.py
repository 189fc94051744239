"""Training the learned rewards on the labels of a pre-tokenised dataset: the rule-based reward (embedding, proxy)
or the done labels (success).

The embedding head reads the frozen action world model's hidden states of real clips (teacher forcing); the proxy
and success networks read frames decoded by the tokenizer, the images they will see inside `roboscape_wm`.
"""

import logging
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch
from accelerate.utils import set_seed
from lerobot.configs.default import DatasetConfig

from lerobot_roboscape.reward.baselines import IMAGE_KINDS, RewardModel, RewardModelConfig
from lerobot_roboscape.tokenizer.modeling_tokenizer import VisualTokenizer
from lerobot_roboscape.training.loop import TrainingConfig, fit
from lerobot_roboscape.world_model.clips import ClipSampler, select_episodes
from lerobot_roboscape.world_model.modeling_world_model import STWorldModel
from lerobot_roboscape.world_model.train import prepare_token_cache
from roboscape_core.errors import InvalidInputError

logger = logging.getLogger(__name__)


@dataclass
class RewardTrainingConfig(TrainingConfig):
    steps: int = 300
    batch_size: int = 8
    lr: float = 1e-3


@dataclass
class TrainRewardConfig:
    """Args:
    reward: the reward model (--reward.kind=embedding|proxy|success, widths).
    dataset: the LeRobot dataset with `next.reward` and `next.success` labels; --dataset.episodes picks the training
        episodes.
    tokenizer: the tokenizer of the world models (local directory or Hub repo id).
    action_world_model: the action world model whose hidden states the embedding head reads (embedding only).
    train: optimisation, logging, checkpoints and resume; batch_size counts clips of the action model's window
        (embedding) or single frames (proxy, success).
    output_dir: checkpoints, logs and the final model (output_dir/pretrained_model).
    cache_dir: where token caches are built and found.
    token_cache: use this existing cache (it must match the dataset and tokenizer).
    device: where to tokenize ("auto": cuda when available).
    """

    reward: RewardModelConfig = field(default_factory=RewardModelConfig)
    dataset: DatasetConfig = field(default_factory=lambda: DatasetConfig(repo_id="local/roboscape"))
    tokenizer: str = "outputs/tokenizer/pretrained_model"
    action_world_model: str = "outputs/world_model_action/pretrained_model"
    train: RewardTrainingConfig = field(default_factory=RewardTrainingConfig)
    output_dir: Path = Path("outputs/reward_model")
    cache_dir: Path = Path("outputs/token_cache")
    token_cache: Path | None = None
    device: str = "auto"


def train_reward_model(cfg: TrainRewardConfig) -> RewardModel:
    cache, _ = prepare_token_cache(cfg.dataset, cfg.tokenizer, cfg.cache_dir, cfg.token_cache, cfg.device)
    tokenizer = VisualTokenizer.from_pretrained(cfg.tokenizer).eval().requires_grad_(False)
    cfg.reward.image_size, cfg.reward.n_cameras = tokenizer.config.image_size, len(cache.cameras)
    episodes = select_episodes(cache, cfg.dataset.episodes)
    images = cfg.reward.kind in IMAGE_KINDS
    world_model, window, frame_skip = None, 1, 1  # an image network reads single frames
    if not images:
        world_model = STWorldModel.from_pretrained(cfg.action_world_model).eval().requires_grad_(False)
        if world_model.config.control != "action":
            raise InvalidInputError(
                f"{cfg.action_world_model} is a {world_model.config.control} world model, not an action one"
            )
        cfg.reward.d_model, window = world_model.config.d_model, world_model.config.window
        frame_skip = world_model.config.frame_skip  # the frames the world model reads
    batches = ClipSampler(cache, episodes, window, cfg.train.batch_size, cfg.train.seed, frame_skip=frame_skip)

    def loss_fn(model, batch):
        with torch.no_grad():
            if images:
                tokenizer.to(batch["tokens"].device)
                inputs = tokenizer.decode_views(batch["tokens"].flatten(0, 1), cfg.reward.n_cameras)
            else:
                world_model.to(batch["tokens"].device)
                control = world_model.encode_control(batch["actions"], batch["no_action"])
                hidden = world_model.compute_hidden(
                    batch["tokens"], control, states=batch["state"], anchor=batch["anchor"]
                )[0]
                inputs = hidden.mean(dim=2).flatten(0, 1)
        labels = batch["done" if cfg.reward.kind == "success" else "reward"]
        return model.compute_loss(inputs, labels.flatten())

    set_seed(cfg.train.seed)
    model = RewardModel(cfg.reward)
    logger.info("training the %s reward on %d episodes of %s", cfg.reward.kind, len(episodes), cache.root)
    return fit(model, loss_fn, batches, cfg.train, cfg.output_dir, asdict(cfg), desc=f"{cfg.reward.kind} reward")
