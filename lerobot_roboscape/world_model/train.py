"""Training a world model (action- or text-conditioned) on a pre-tokenised LeRobot dataset."""

import copy
import json
import logging
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from accelerate.utils import set_seed
from lerobot.configs.default import DatasetConfig
from lerobot.datasets.compute_stats import aggregate_feature_stats
from lerobot.utils.constants import ACTION, OBS_STATE

from lerobot_roboscape.dataset.reader import DONE_LABEL_COLUMNS, open_dataset
from lerobot_roboscape.tokenizer.modeling_tokenizer import VisualTokenizer
from lerobot_roboscape.tokenizer.similarity import TokenizerPerceptualDistance
from lerobot_roboscape.tokenizer.token_cache import (
    STATS_FILE,
    STATS_KEYS,
    TokenCache,
    dataset_fingerprint,
    load_or_build_token_cache,
    open_token_cache,
    tokenizer_fingerprint,
)
from lerobot_roboscape.training.checkpoints import FINAL
from lerobot_roboscape.training.loop import TrainingConfig, fit, resolve_device, save_atomically
from lerobot_roboscape.world_model.clips import ClipMixture, ClipSampler, ResidentClips, select_episodes
from lerobot_roboscape.world_model.configuration_world_model import TinyWorldModelConfig, WorldModelConfig
from lerobot_roboscape.world_model.done_tuning import done_features, tune_done_head
from lerobot_roboscape.world_model.goals import goal_summary, load_goal_starts
from lerobot_roboscape.world_model.measures.controllability import (
    control_summary,
    load_control_starts,
    read_control_set,
)
from lerobot_roboscape.world_model.modeling_world_model import STWorldModel
from roboscape_core.errors import InvalidInputError

logger = logging.getLogger(__name__)
TOKENIZER_FINGERPRINT = "tokenizer_fingerprint"  # in the run's TRAIN_CONFIG: the tokens the model learned


@dataclass
class WorldModelTrainingConfig(TrainingConfig):
    """Args (beside TrainingConfig's):
    resident: hold the token caches whole on the training device and slice each step's clips there
        (ResidentClips), so that a step sends only row indices; null: on a GPU.
    """

    steps: int = 800
    batch_size: int = 8
    lr: float = 1e-3
    resident: bool | None = None


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
    token_cache: use this existing cache; it must match the dataset and tokenizer. One imported from an exported file
        (tokenizer/token_cache.py: import_token_cache) is read without its dataset.
    only_optimal: train on optimal episodes only (default: yes for the text model, no for the action model).
    only_successful: train on successful episodes only (default: yes for the text model, no for the action model).
    exploration: exploratory episodes for the action model (`roboscape-collect --kinds=[noisy,excursion,random]`),
        a dataset of their own; null: none. Its actions join the demonstrations' in the normalisation statistics.
    exploration_share: share of the action model's training clips drawn from `exploration`.
    exploration_token_cache: use this existing cache of `exploration`, as token_cache.
    heldout_control: a controllability set (`roboscape-collect-control`, OOD starts) on which the action model's
        retrieval and action gain are read every --train.eval_freq steps (output_dir/heldout_curve.jsonl).
    heldout_horizon: control steps of those rollouts.
    heldout_starts: controllability sets already read (`measures/controllability.py`: save_control_starts, e.g. on
        a machine without the datasets' videos), measured beside heldout_control; the curve names each measure
        after its file (`<file stem>/retrieval_whole_frame`).
    done_tuning_steps: after training, fit the done head alone on the model's own open-loop frames of training
        episodes and on their real frames, for this many full-batch steps, so that it fires where roboscape_wm
        reads it (world_model/done_tuning.py); 0: off. The action model only.
    done_tuning_episodes: training episodes generated open loop for it, spread over the episodes (null: all).
    init_from: a trained world model (a local directory or Hub repo id) to start from instead of random weights. Its
        configuration is kept (layout, action statistics; --wm is not read but for its control, which must match)
        and the data must fit its layout.
    retrain_blocks: with init_from, draw the last this many blocks and the heads after them afresh (from
        --train.seed) and train those alone, the rest frozen: a member of an ensemble that shares the model's trunk
        and parts in its top, for a fraction of a whole model's training (bootstrapped DQN's heads); null: every
        weight is trained on from init_from's.
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
    exploration: DatasetConfig | None = None
    exploration_share: float = 0.5
    exploration_token_cache: Path | None = None
    heldout_control: DatasetConfig | None = None
    heldout_horizon: int = 16
    heldout_starts: list[Path] = field(default_factory=list)
    heldout_goals: list[Path] = field(default_factory=list)
    heldout_theta: float = 0.9
    done_tuning_steps: int = 300
    done_tuning_episodes: int | None = 128
    init_from: str | None = None
    retrain_blocks: int | None = None
    device: str = "auto"

    def __post_init__(self):
        if self.exploration is not None and self.wm.control != "action":
            raise InvalidInputError(
                f"exploration={self.exploration.repo_id}: exploratory episodes train the action world model only, "
                f"not the {self.wm.control} one"
            )
        if (self.heldout_control is not None or self.heldout_starts) and self.wm.control != "action":
            raise InvalidInputError("heldout_control measures the action world model; the text model has no actions")
        if self.heldout_goals and self.wm.control != "text":
            raise InvalidInputError("heldout_goals judge the text model's goals; the action model has none")
        if not 0 < self.heldout_theta <= 1:
            raise InvalidInputError(f"heldout_theta must be in (0, 1], got {self.heldout_theta}")
        for name, paths, writer in (
            ("heldout_starts", self.heldout_starts, "save_control_starts"),
            ("heldout_goals", self.heldout_goals, "save_goal_starts"),
        ):
            for path in paths:
                if not Path(path).is_file():
                    raise InvalidInputError(f"{name}: {path} is not a file ({writer} writes one)")
        if not 0.0 <= self.exploration_share <= 1.0:
            raise InvalidInputError(f"exploration_share must be in [0, 1], got {self.exploration_share}")
        if self.retrain_blocks is not None and self.init_from is None:
            raise InvalidInputError(
                f"retrain_blocks={self.retrain_blocks} retrains the top of init_from's model; give init_from"
            )


def prepare_token_cache(
    dataset_cfg: DatasetConfig,
    tokenizer_path: str,
    cache_dir: Path,
    token_cache: Path | None = None,
    device: str = "auto",
) -> tuple[TokenCache, dict]:
    """The token cache of every episode of the dataset under this tokenizer, built on first use, and the dataset's
    statistics of its actions and states (LeRobot's dataset.meta.stats of STATS_KEYS). A cache imported from an
    exported file (import_token_cache) carries those statistics and is read without its dataset."""
    tokenizer = VisualTokenizer.from_pretrained(tokenizer_path)
    if token_cache is not None and (Path(token_cache) / STATS_FILE).is_file():
        cache = open_token_cache(token_cache, tokenizer_fp=tokenizer_fingerprint(tokenizer))
        stats = json.loads((Path(token_cache) / STATS_FILE).read_text())
        return cache, {key: {k: np.asarray(v) for k, v in stats[key].items()} for key in STATS_KEYS}
    dataset = open_dataset(dataset_cfg.repo_id, dataset_cfg.root)  # the cache covers all episodes
    stats = {key: dataset.meta.stats[key] for key in STATS_KEYS if key in dataset.meta.stats}  # state: optional
    if token_cache is not None:
        cache = open_token_cache(token_cache, dataset_fingerprint(dataset.root), tokenizer_fingerprint(tokenizer))
    else:
        cache = load_or_build_token_cache(dataset, tokenizer, cache_dir, device=resolve_device(device))
    return cache, stats


def check_same_layout(cache: TokenCache, other: TokenCache) -> None:
    """Two token caches one model trains on must share the frame layout and the action width."""
    names = ("cameras", "tokens_per_side", "vocab_size", "action_dim", "state_dim")
    if differ := {n: (getattr(cache, n), getattr(other, n)) for n in names if getattr(cache, n) != getattr(other, n)}:
        raise InvalidInputError(f"token caches {cache.root} and {other.root} differ in {differ}")


# The data's statistics a world model keeps: (its config's prefix, the dataset's key, the moments).
STATISTICS_KEPT = (("action", ACTION, ("mean", "std")), ("state", OBS_STATE, ("mean", "std", "min", "max")))


def fit_config_to_cache(wm: WorldModelConfig, cache: TokenCache, stats: dict) -> WorldModelConfig:
    """A copy of `wm` whose frame layout, action and state widths and their statistics (the states' range too) come
    from the data; says so when the layout differs from the preset. The caller's config stays as it was given (a
    pipeline records it)."""
    wm = copy.deepcopy(wm)
    for name, value in (
        ("n_cameras", len(cache.cameras)),
        ("tokens_per_side", cache.tokens_per_side),
        ("vocab_size", cache.vocab_size),
        ("action_dim", cache.action_dim),
        ("state_dim", cache.state_dim),
    ):
        if getattr(wm, name) != value:
            logger.info("wm.%s = %s (from the token cache; the preset had %s)", name, value, getattr(wm, name))
            setattr(wm, name, value)
    for name, key, moments in STATISTICS_KEPT:
        if key not in stats:  # a dataset without states: the state channel is off (check_cache_fits)
            continue
        for moment in moments:
            setattr(wm, f"{name}_{moment}", np.asarray(stats[key][moment], dtype=np.float64).reshape(-1).tolist())
    wm.__post_init__()  # the statistics must fit the action and state layouts
    return wm


def check_cache_fits(wm: WorldModelConfig, cache: TokenCache, dataset: str) -> None:
    """The columns the model's parts learn from, which a user's dataset may lack: one line naming the column and the
    flag that turns that part off."""
    if wm.done_weight > 0 and not cache.has_done_labels:
        raise InvalidInputError(
            f"dataset {dataset} has no {' or '.join(map(repr, DONE_LABEL_COLUMNS))} column, which the done head "
            "learns from: add one, or train without the done loss with --wm.done_weight=0"
        )
    if wm.state and cache.state_dim == 0:
        raise InvalidInputError(
            f"dataset {dataset} has no '{OBS_STATE}' column, which the state channel reads: pass --wm.state=false"
        )


def train_world_model(cfg: TrainWorldModelConfig) -> STWorldModel:
    cache, stats = prepare_token_cache(cfg.dataset, cfg.tokenizer, cfg.cache_dir, cfg.token_cache, cfg.device)
    check_cache_fits(cfg.wm, cache, cfg.dataset.root or cfg.dataset.repo_id)
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
    sampler = ClipSampler(
        cache, episodes, cfg.wm.window, cfg.train.batch_size, cfg.train.seed, frame_skip=cfg.wm.frame_skip
    )
    # The tokenizer's fingerprint names the tokens the model reads: a run that takes the model checks it.
    run_config = {**asdict(cfg), "token_cache": str(cache.root)}
    run_config[TOKENIZER_FINGERPRINT] = cache.manifest["tokenizer_fingerprint"]
    batches = sampler
    if cfg.exploration is not None:
        explore_cache, explore_stats = prepare_token_cache(
            cfg.exploration, cfg.tokenizer, cfg.cache_dir, cfg.exploration_token_cache, cfg.device
        )
        check_same_layout(cache, explore_cache)
        explore_episodes = select_episodes(explore_cache, cfg.exploration.episodes)
        logger.info(
            "and on %d exploratory episodes of %s, %.0f%% of the clips",
            len(explore_episodes),
            explore_cache.root,
            100 * cfg.exploration_share,
        )
        explore = ClipSampler(
            explore_cache, explore_episodes, cfg.wm.window, cfg.train.batch_size, cfg.train.seed, cfg.wm.frame_skip
        )
        share = cfg.exploration_share
        batches = ClipMixture([sampler, explore], [1 - share, share], cfg.train.batch_size, cfg.train.seed)
        stats = {key: aggregate_feature_stats([stats[key], explore_stats[key]]) for key in stats}
        run_config["exploration_token_cache"] = str(explore_cache.root)
    device = resolve_device("auto")  # where fit trains (Accelerate's choice)
    if cfg.train.resident if cfg.train.resident is not None else device == "cuda":
        batches = ResidentClips(batches, device)
        logger.info("token caches resident on %s: %.0f MiB", device, batches.nbytes / 2**20)
    set_seed(cfg.train.seed)  # the initial weights too, so a run is reproducible
    if cfg.init_from is None:
        model = STWorldModel(fit_config_to_cache(cfg.wm, cache, stats))
    else:
        model = start_from(cfg.init_from, cfg.retrain_blocks, cache, cfg.wm.control)
    model = fit(
        model,
        lambda m, batch: m(batch),
        batches,
        cfg.train,
        cfg.output_dir,
        run_config,
        desc=f"{cfg.wm.control} world model",
        evaluate=heldout_evaluation(cfg),
        flops_per_sample=model.training_flops_per_clip(),
    )
    if cfg.done_tuning_steps and cfg.wm.control == "action":
        tune_done_on_open_loop(model, cache, episodes, cfg)
    return model


def start_from(init_from: str, retrain_blocks: int | None, cache: TokenCache, control: str) -> STWorldModel:
    """A trained model to train on: whole, or its top drawn afresh and trainable alone (`retrain_blocks`)."""
    model = STWorldModel.from_pretrained(init_from)
    c = model.config
    theirs = {"control": c.control, "n_cameras": c.n_cameras, "tokens_per_side": c.tokens_per_side}
    theirs |= {"vocab_size": c.vocab_size, "action_dim": c.action_dim}
    ours = {"control": control, "n_cameras": len(cache.cameras), "tokens_per_side": cache.tokens_per_side}
    ours |= {"vocab_size": cache.vocab_size, "action_dim": cache.action_dim}
    if differ := {name: (theirs[name], ours[name]) for name in ours if theirs[name] != ours[name]}:
        raise InvalidInputError(f"init_from={init_from}: the model and the data (or --wm.control) differ in {differ}")
    if retrain_blocks is not None:
        trained = sum(p.numel() for p in model.redraw_top(retrain_blocks).parameters())
        logger.info(
            "init_from %s: its last %d blocks and heads drawn afresh, %d of %d weights trained",
            init_from,
            retrain_blocks,
            trained,
            sum(p.numel() for p in model.parameters()),
        )
    return model


def tune_done_on_open_loop(model: STWorldModel, cache: TokenCache, episodes: list[dict], cfg: TrainWorldModelConfig):
    """The done head refitted on open-loop and real frames of training episodes; the model saved again with it."""
    n = cfg.done_tuning_episodes or len(episodes)
    picked = [episodes[i] for i in np.linspace(0, len(episodes) - 1, min(n, len(episodes))).round().astype(int)]
    model.eval()
    features, labels, open_loop = done_features(model, cache, picked)
    losses = tune_done_head(model, features, labels, cfg.done_tuning_steps)
    with torch.no_grad():
        after = torch.sigmoid(model.done_head(features.to(next(model.parameters()).device)).squeeze(-1)).cpu()
    summary = {
        "episodes": len(picked),
        "frames": {"open_loop": int(open_loop.sum()), "real": int((~open_loop).sum())},
        "loss": {"first": losses[0], "last": losses[-1]},
        "mean_done_of_positive_open_loop_frames": float(after[open_loop & (labels > 0.5)].mean()),
        "mean_done_of_negative_open_loop_frames": float(after[open_loop & (labels <= 0.5)].mean()),
    }
    logger.info("done head tuned on open-loop frames: %s", summary)
    (Path(cfg.output_dir) / "done_tuning.json").write_text(json.dumps(summary, indent=2))
    save_atomically(model, Path(cfg.output_dir) / FINAL)


def heldout_evaluation(cfg: TrainWorldModelConfig):
    """What the run reads along training: the action model's controllability, the text model's goals, or nothing."""
    if cfg.heldout_control is not None or cfg.heldout_starts:
        return heldout_control(cfg)
    return heldout_goals(cfg) if cfg.heldout_goals else None


def heldout_goals(cfg: TrainWorldModelConfig):
    """The held-out evaluation of the text model: its goals from each goal set of heldout_goals (named by its
    file)."""
    device = resolve_device(cfg.device)
    tokenizer = VisualTokenizer.from_pretrained(cfg.tokenizer).to(device).eval()
    distance = TokenizerPerceptualDistance(tokenizer).to(device)
    sets = {Path(path).stem: load_goal_starts(path, device) for path in cfg.heldout_goals}
    return lambda model: {
        f"{name}/{measure}": value
        for name, starts in sets.items()
        for measure, value in goal_summary(
            model, tokenizer, distance, starts, cfg.heldout_theta, cfg.wm.frame_skip
        ).items()
    }


def heldout_control(cfg: TrainWorldModelConfig):
    """The held-out evaluation of the action model: retrieval and action gain on the controllability set, and on
    each saved set of heldout_starts (named by its file)."""
    device = resolve_device(cfg.device)
    tokenizer = VisualTokenizer.from_pretrained(cfg.tokenizer).to(device).eval()
    sets = {}
    if cfg.heldout_control is not None:
        dataset = open_dataset(cfg.heldout_control.repo_id, cfg.heldout_control.root, cfg.heldout_control.episodes)
        sets[""] = read_control_set(dataset, tokenizer, cfg.wm.frame_skip, cfg.heldout_horizon, device)
    for path in cfg.heldout_starts:
        sets[f"{Path(path).stem}/"] = load_control_starts(path, cfg.wm.frame_skip, device)
    return lambda model: {
        f"{name}{measure}": value
        for name, starts in sets.items()
        for measure, value in control_summary(model, tokenizer, starts).items()
    }
