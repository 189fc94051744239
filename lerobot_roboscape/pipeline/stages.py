"""The stages of the pipeline, one function each: each takes the run's config and what the stages before it made,
and returns what it made. A stage writes into its own folder under output_dir and, once complete, a stage.json with
the settings it ran with; a rerun with the same settings skips it (so a killed run resumes where it stopped)."""

import logging
from dataclasses import dataclass, replace
from pathlib import Path

import av
import imageio.v3 as iio
import numpy as np
from lerobot.configs.default import DatasetConfig

from lerobot_roboscape.dataset.reader import episode_facts, open_dataset, successful_episodes
from lerobot_roboscape.envs.configs import RoboscapeWorldModelEnvConfig
from lerobot_roboscape.envs.reward_report import (
    RewardReportConfig,
    plot_rollout_rewards,
    read_reward_report,
    write_reward_report,
)
from lerobot_roboscape.envs.world_model_env import RoboscapeWorldModelEnv
from lerobot_roboscape.pipeline.config import PipelineConfig
from lerobot_roboscape.pipeline.data_stages import Datasets
from lerobot_roboscape.pipeline.given import GIVEN_TOKENIZER, brought, given_tokenizer, given_world_model
from lerobot_roboscape.pipeline.layout import (
    DONE_REPORT_DIR,
    DONE_REPORT_IND_DIR,
    REWARD_REPORT_DIR,
    TOKEN_CACHE_DIR,
    TOKENIZER_DIR,
    TOKENIZER_REPORT_DIR,
    WorldModelPaths,
    fidelity_dir,
    reward_model_dir,
    world_model_dir,
)
from lerobot_roboscape.pipeline.methods import (
    REWARD_BASELINES,
    SUCCESS_CLASSIFIER,
)
from lerobot_roboscape.pipeline.resume import run_once, train_once
from lerobot_roboscape.reward.baselines import RewardModelConfig
from lerobot_roboscape.reward.done_report import DoneChoice, DoneReportConfig, evaluate_done
from lerobot_roboscape.reward.train import TrainRewardConfig, train_reward_model
from lerobot_roboscape.tokenizer.report import TokenizerReportConfig, evaluate_tokenizer, read_tokenizer_report
from lerobot_roboscape.tokenizer.train import TrainTokenizerConfig, train_tokenizer
from lerobot_roboscape.training.checkpoints import FINAL
from lerobot_roboscape.training.loop import TrainingConfig
from lerobot_roboscape.world_model.measures.fidelity import FidelityConfig, evaluate_fidelity, read_fidelity
from lerobot_roboscape.world_model.train import TrainWorldModelConfig, train_world_model

logger = logging.getLogger(__name__)
# ---- models ------------------------------------------------------------------------------------------------------


def tokenizer(cfg: PipelineConfig, out: Path, data: Datasets) -> Path:
    """Train the image tokenizer, measured on the held-out episodes as it trains; returns its pretrained_model
    directory. When --world_models brings the tokenizer they learned, that one is taken instead."""
    folder = out / TOKENIZER_DIR
    if GIVEN_TOKENIZER in brought(cfg):
        return given_tokenizer(cfg, folder)
    train = TrainTokenizerConfig(
        dataset=data.train,
        heldout=data.heldout,
        tokenizer=cfg.tokenizer,
        train=_with_checkpoints(cfg.tokenizer_train),
        output_dir=folder,
        num_workers=min(cfg.data.workers, 2),
        allow_random_lpips=True,
    )
    return _train(folder, train, train_tokenizer, cfg.fresh)


def tokenizer_report(cfg: PipelineConfig, out: Path, data: Datasets, tokenizer_path: Path) -> dict:
    """The tokenizer's report on every held-out frame (whole frame and object, per view); returns it."""
    folder = out / TOKENIZER_REPORT_DIR
    report_cfg = TokenizerReportConfig(
        dataset=data.heldout,
        tokenizer=str(tokenizer_path),
        output_dir=folder,
        training_dir=out / TOKENIZER_DIR,
        device=cfg.device,
    )
    run_once(folder, report_cfg, cfg.fresh, lambda: evaluate_tokenizer(report_cfg))
    return read_tokenizer_report(folder)


def world_models(cfg: PipelineConfig, out: Path, data: Datasets, tokenizer_path: Path) -> WorldModelPaths:
    """Train the action and the text world models (each with its done head); returns their folders. The
    action model also trains on the exploratory episodes, and reads its retrieval and action gain on the
    controllability set as it trains. Those --world_models brings are taken instead."""
    given = brought(cfg)
    return WorldModelPaths(
        *(
            given_world_model(cfg, out, tokenizer_path, control)
            if control in given
            else _world_model(cfg, out / world_model_dir(control), data, tokenizer_path, control, training)
            for control, training in zip(WorldModelPaths._fields, (cfg.wm_train, cfg.text_wm_train), strict=True)
        )
    )


def ensemble_members(
    cfg: PipelineConfig,
    out: Path,
    data: Datasets,
    tokenizer_path: Path,
    n: int,
    retrain_blocks: int | None,
    steps_share: float,
) -> list[Path]:
    """`n` more action world models, an ensemble whose disagreement guards PPO in the world model
    (envs/ensemble.py), for `steps_share` of the run's own model's steps each, seeds 1..n: the run's model with its
    last `retrain_blocks` blocks and heads drawn afresh and trained alone, or (null) whole models trained as the
    run's own. Members feed the disagreement only: their done heads are not tuned."""
    own = out / world_model_dir("action") / FINAL
    tag = "action_seed" if retrain_blocks is None else f"action_top{retrain_blocks}_seed"
    steps, members = max(round(cfg.wm_train.steps * steps_share), 1), []
    for seed in range(1, n + 1):
        training = replace(cfg.wm_train, seed=seed, steps=steps)
        start = {"init_from": str(own), "retrain_blocks": retrain_blocks} if retrain_blocks is not None else {}
        folder = out / world_model_dir(f"{tag}{seed}")
        members.append(
            _world_model(cfg, folder, data, tokenizer_path, "action", training, done_tuning_steps=0, **start)
        )
    return members


def _world_model(
    cfg: PipelineConfig, folder: Path, data: Datasets, tokenizer_path: Path, control: str, training, **train_options
) -> Path:
    action = control == "action"
    train = TrainWorldModelConfig(
        dataset=data.train,
        tokenizer=str(tokenizer_path),
        # corrupted context was judged on the action model's rollouts (corrupt70); the text model's goals without it
        wm=replace(cfg.wm, control=control, corrupt_max=cfg.wm.corrupt_max if action else 0.0),
        train=_with_checkpoints(training),
        output_dir=folder,
        cache_dir=folder.parent / TOKEN_CACHE_DIR,
        exploration=data.exploration if action else None,
        exploration_share=cfg.exploration_share,
        heldout_control=data.controllability if action else None,
        device=cfg.device,
        **train_options,
    )
    return _train(folder, train, train_world_model, cfg.fresh)


def _with_checkpoints(training: TrainingConfig) -> TrainingConfig:
    """A checkpoint every quarter of the run and a held-out reading every tenth, whatever its length."""
    return replace(training, save_freq=max(training.steps // 4, 1), eval_freq=max(training.steps // 10, 1))


def _train(folder: Path, train, trainer, fresh: bool) -> Path:
    """Run `trainer` on its config `train` into `folder` unless done, resuming a killed run of the same settings
    from its checkpoints; returns the final model."""
    train_once(folder, train, fresh, lambda resume: trainer(replace(train, train=replace(train.train, resume=resume))))
    return folder / FINAL


def reward_models(
    cfg: PipelineConfig, out: Path, data: Datasets, tokenizer_path: Path, models: WorldModelPaths
) -> dict[str, Path]:
    """Train the paper's baseline rewards (embedding-based and proxy-based) and the success classifier; {} when
    the run trains no reward models."""
    trained = {}
    for kind in (*REWARD_BASELINES, SUCCESS_CLASSIFIER) if cfg.reward_models else ():
        folder = out / reward_model_dir(kind)
        train = TrainRewardConfig(
            reward=RewardModelConfig(kind=kind),
            dataset=data.train,
            tokenizer=str(tokenizer_path),
            action_world_model=str(models.action),
            # The embedding head reads clips of the action model's window; the image networks single frames.
            train=replace(cfg.reward_train, batch_size=8 if kind == "embedding" else 32),
            output_dir=folder,
            cache_dir=out / TOKEN_CACHE_DIR,
            device=cfg.device,
        )
        run_once(folder, train, cfg.fresh, lambda t=train: train_reward_model(t))
        trained[kind] = folder / FINAL
    return trained


def done_report(
    cfg: PipelineConfig, out: Path, data: Datasets, tokenizer_path: Path, models: WorldModelPaths, trained: dict
) -> DoneChoice:
    """Which done signal the env trusts (the action model's head or the success classifier) and its threshold,
    chosen on the validation episodes and measured on the held-out ones (the report, in its folder). Where the
    validation episodes are a collection of their own, half of them choose and the other half judge the same choice
    in domain (its report in DONE_REPORT_IND_DIR)."""
    folder = out / DONE_REPORT_DIR
    classifier = trained.get(SUCCESS_CLASSIFIER)
    validation, judge_ind = data.validation, None
    if data.validation.root != data.train.root:  # a collection of its own: half chooses, half judges in domain
        validation, judge_ind = halves(data.validation)
    report_cfg = DoneReportConfig(
        dataset=spread(data.heldout, cfg.data.report_episodes),
        validation=validation,
        tokenizer=str(tokenizer_path),
        world_model=str(models.action),
        success_classifier=_str(classifier),
        output_dir=folder,
        device=cfg.device,
    )
    run_once(folder, report_cfg, cfg.fresh, lambda: evaluate_done(report_cfg))
    if judge_ind is not None:  # the same choice (same models, same validation half), judged on the other half
        ind_cfg = replace(report_cfg, dataset=judge_ind, output_dir=out / DONE_REPORT_IND_DIR)
        run_once(ind_cfg.output_dir, ind_cfg, cfg.fresh, lambda: evaluate_done(ind_cfg))
    return DoneChoice.read(folder)


def halves(dataset: DatasetConfig) -> tuple[DatasetConfig, DatasetConfig]:
    """The dataset's episodes in two halves, each holding every other episode of each (family, outcome): one to
    choose the done threshold on, one to judge it (the set that picks a threshold cannot judge it)."""
    d = open_dataset(dataset.repo_id, dataset.root)
    succeeded, groups = set(successful_episodes(d)), {}
    for i in range(d.meta.total_episodes):
        groups.setdefault((episode_facts(d, i)["task_family"], i in succeeded), []).append(i)
    first, second = (sorted(i for group in groups.values() for i in group[k::2]) for k in (0, 1))
    return replace(dataset, episodes=first), replace(dataset, episodes=second)


def world_model_env(
    cfg: PipelineConfig,
    demonstrations: DatasetConfig,
    tokenizer_path: Path,
    models: WorldModelPaths,
    done: DoneChoice | None = None,
    trained: dict | None = None,
) -> RoboscapeWorldModelEnvConfig:
    """The `roboscape_wm` env of these models, starting from the demonstrations' first frames; with the done
    report's choice, its done source and threshold (for success, the goal and the sparse reward)."""
    chosen = dict(done_source="world_model")
    if done is not None:
        classifier = (trained or {}).get(SUCCESS_CLASSIFIER) if done.source == "classifier" else None
        chosen = dict(
            done_source=done.source, success_classifier=_str(classifier), theta=done.theta, theta_sps=done.theta
        )
    return RoboscapeWorldModelEnvConfig(
        dataset_repo_id=demonstrations.repo_id,
        dataset_root=demonstrations.root,
        tokenizer=str(tokenizer_path),
        action_world_model=str(models.action),
        text_world_model=str(models.text),
        families=cfg.data.families,
        image_size=cfg.data.image_size,
        max_goal_steps=cfg.env.max_goal_steps,
        allow_random_lpips=True,
        device=cfg.device,
        **chosen,
    )


def spread(dataset: DatasetConfig, k: int) -> DatasetConfig:
    """`k` episodes of the dataset evenly spaced over it (episodes are stored family by family and scene by
    scene, so the first k would all be of one family)."""
    n = open_dataset(dataset.repo_id, dataset.root).meta.total_episodes
    episodes = sorted({int(i) for i in np.linspace(0, n - 1, min(k, n)).round()})
    return replace(dataset, episodes=episodes)


# ---- reports on the models ---------------------------------------------------------------------------------------


def fidelity(
    cfg: PipelineConfig, out: Path, data: Datasets, tokenizer_path: Path, models: WorldModelPaths, domain: str = "ood"
) -> dict | None:
    """The action world model's fidelity report (PSNR per open-loop step against the tokenizer's own reconstruction,
    with the controllability reading) on held-out OOD episodes or, `domain="ind"`, on the validation episodes and
    the controllability set of new starts in the training scenes; returns the report (None: the scale has no IND
    set)."""
    folder = out / fidelity_dir(domain)
    if domain == "ind":
        if data.controllability_ind is None:
            return None
        episodes, control = data.validation, data.controllability_ind
    else:
        episodes, control = data.heldout, data.controllability
    report_cfg = FidelityConfig(
        dataset=spread(episodes, cfg.data.report_episodes),
        tokenizer=str(tokenizer_path),
        world_model=str(models.action),
        output_dir=folder,
        max_episodes=cfg.data.report_episodes,
        controllability=control,
        allow_random_lpips=True,
        device=cfg.device,
    )
    run_once(folder, report_cfg, cfg.fresh, lambda: evaluate_fidelity(report_cfg))
    return read_fidelity(folder)


def reward_report(
    cfg: PipelineConfig, out: Path, data: Datasets, env: RoboscapeWorldModelEnvConfig, baselines: dict[str, Path]
) -> dict:
    """Every reward along the held-out episodes and how well its return separates success from failure."""
    folder = out / REWARD_REPORT_DIR
    report_cfg = RewardReportConfig(
        env=env,
        dataset=spread(data.heldout, cfg.data.report_episodes),
        embedding_reward=_str(baselines.get("embedding")),
        proxy_reward=_str(baselines.get("proxy")),
        output_dir=folder,
        max_episodes=cfg.data.report_episodes,
    )
    # The report points a copy of the env at the held-out data, every episode of it (a converted dataset records
    # no task family to filter by).
    run_once(
        folder, report_cfg, cfg.fresh, lambda: write_reward_report(replace(report_cfg, env=replace(env, families=[])))
    )
    return read_reward_report(folder)


def _str(path: Path | None) -> str | None:
    return None if path is None else str(path)


@dataclass(frozen=True)
class WorldModelRollout:
    """What `world_model_rollout` made: its video (frame beside goal), its reward plot, and its episodes' returns."""

    video: Path
    plot: Path
    steps: int
    episodes: int
    returns: list[float]


def world_model_rollout(
    out: Path, env_cfg: RoboscapeWorldModelEnvConfig, episodes: int = 2, steps: int = 40
) -> WorldModelRollout:
    """Random actions in `roboscape_wm`: a video of frame beside goal and the reward curve."""
    env = RoboscapeWorldModelEnv(replace(env_cfg, episode_length=steps), num_envs=episodes)
    env.reset(seed=0)
    frames, rewards = [np.concatenate(env.render(), axis=1)], []
    rng = np.random.default_rng(0)
    for _ in range(steps):
        _, reward, terminated, truncated, _ = env.step(rng.uniform(-1, 1, env.action_space.shape).astype(np.float32))
        frames.append(np.concatenate(env.render(), axis=1))
        rewards.append(reward)
        if (terminated | truncated).all():
            break
    rewards = np.stack(rewards)
    video, plot = out / "wm_rollout.mp4", out / "wm_rollout_reward.png"
    av.logging.set_level(av.logging.ERROR)
    iio.imwrite(video, np.stack(frames), plugin="pyav", codec="libx264", fps=env.metadata["render_fps"])
    plot_rollout_rewards(rewards, env.tasks(), plot)
    return WorldModelRollout(video, plot, len(rewards), episodes, [round(float(r), 2) for r in rewards.sum(0)])
