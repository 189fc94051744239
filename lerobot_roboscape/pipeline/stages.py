"""The stages of the pipeline, one function each: each takes the run's config and what the stages before it made,
and returns what it made. A stage writes into its own folder under output_dir and, once complete, a stage.json with
the settings it ran with; a rerun with the same settings skips it (so a killed run resumes where it stopped)."""

import json
import logging
import shutil
from dataclasses import dataclass, replace
from pathlib import Path

import av
import imageio.v3 as iio
import numpy as np
from lerobot.configs.default import DatasetConfig

from lerobot_roboscape.dataset.convert import ConvertConfig, convert
from lerobot_roboscape.dataset.reader import open_dataset
from lerobot_roboscape.demos.collect import CollectConfig, collect, episodes_dir
from lerobot_roboscape.demos.controllability import ControllabilityConfig, collect_controllability
from lerobot_roboscape.demos.exploration import EXPLORATORY_KINDS
from lerobot_roboscape.demos.record import record_maniskill_trajectories
from lerobot_roboscape.envs.configs import RoboscapeWorldModelEnvConfig
from lerobot_roboscape.envs.reward_report import RewardReportConfig, plot_rollout_rewards, write_reward_report
from lerobot_roboscape.envs.world_model_env import RoboscapeWorldModelEnv
from lerobot_roboscape.pipeline.config import PipelineConfig
from lerobot_roboscape.pipeline.layout import (
    CONTROL_DIR,
    CONTROL_IND_DIR,
    CONVERTED_DIR,
    DEMOS_DIR,
    DEMOS_REPO_ID,
    DONE_REPORT_DIR,
    EXPLORE_DIR,
    HELDOUT_DIR,
    REWARD_REPORT_DIR,
    TOKEN_CACHE_DIR,
    TOKENIZER_DIR,
    TOKENIZER_REPORT_DIR,
    TRAJECTORIES_DIR,
    VALIDATION_DIR,
    fidelity_dir,
    reward_model_dir,
    world_model_dir,
)
from lerobot_roboscape.pipeline.methods import (
    REWARD_BASELINES,
    SUCCESS_CLASSIFIER,
)
from lerobot_roboscape.pipeline.resume import STAGE_FILE, is_done, mark_done, run_once, start, train_once
from lerobot_roboscape.reward.baselines import RewardModelConfig
from lerobot_roboscape.reward.done_report import DoneReportConfig, evaluate_done
from lerobot_roboscape.reward.train import RewardTrainingConfig, TrainRewardConfig, train_reward_model
from lerobot_roboscape.tasks import select_scenes
from lerobot_roboscape.tokenizer.configuration_tokenizer import TokenizerConfig
from lerobot_roboscape.tokenizer.report import TokenizerReportConfig, evaluate_tokenizer
from lerobot_roboscape.tokenizer.train import TokenizerTrainingConfig, TrainTokenizerConfig, train_tokenizer
from lerobot_roboscape.training.checkpoints import FINAL
from lerobot_roboscape.world_model.configuration_world_model import WorldModelConfig
from lerobot_roboscape.world_model.fidelity import FidelityConfig, evaluate_fidelity
from lerobot_roboscape.world_model.train import TrainWorldModelConfig, WorldModelTrainingConfig, train_world_model

logger = logging.getLogger(__name__)
HELDOUT_SEED = 50_000  # held-out episodes get initial states that the training collection (seeds from 0) lacks
VALIDATION_SEED = 60_000  # so do the validation episodes the done threshold is chosen on
CONTROL_SEED = 70_000  # and the starts of the controllability set
CONTROL_IND_SEED = 75_000  # and those of its twin in the training scenes
EXPLORE_SEED = 80_000  # and the exploratory episodes


# ---- data --------------------------------------------------------------------------------------------------------


@dataclass
class Datasets:
    """train: the demonstrations (IND scenes; successful, suboptimal and failed attempts). heldout: episodes the
    models never saw, for the fidelity and reward reports (OOD scenes, half failed; or one converted episode).
    validation: episodes the done threshold is chosen on (IND scenes, new initial states, half failed; the
    demonstrations themselves at the scales without held-out scenes). controllability: K action sequences from
    each of some OOD starts (demos/controllability.py), or None; controllability_ind: the same from new initial
    states of the training scenes (where RL runs, so where the world model must first be faithful), or None.
    trajectory_file: the recorded ManiSkill .h5 that
    `roboscape-convert` read. exploration: exploratory episodes in the IND scenes (demos/exploration.py) for the
    action world model only, or None."""

    train: DatasetConfig
    heldout: DatasetConfig
    validation: DatasetConfig
    controllability: DatasetConfig | None
    trajectory_file: Path
    exploration: DatasetConfig | None = None
    controllability_ind: DatasetConfig | None = None


def _collect(cfg: CollectConfig, fresh: bool) -> DatasetConfig:
    folder = Path(cfg.root)
    if fresh:
        shutil.rmtree(episodes_dir(folder), ignore_errors=True)
    # a killed collection continues from the episodes it saved (its planned jobs must match, or collect says so)
    run_once(folder, cfg, fresh, lambda: collect(replace(cfg, overwrite=True, resume=True)))
    return DatasetConfig(repo_id=cfg.repo_id, root=str(folder))


def _unseen_episodes(
    cfg: PipelineConfig, root: Path, split: str, scenes: int | None, per_scene: int, seed: int
) -> DatasetConfig:
    """Episodes no model trains on, from initial states the demonstrations lack: half of them failed attempts,
    with the object's masks (the held-out and the validation collections)."""
    return _collect(
        CollectConfig(
            repo_id=f"local/{root.name}",
            root=str(root),
            families=cfg.families,
            split=split,
            max_scenes=scenes,
            episodes_per_scene=per_scene,
            failed_fraction=0.5,
            seed=seed,
            image_size=cfg.image_size,
            workers=cfg.workers,
            keep_failed=True,
            segmentation=True,
        ),
        cfg.fresh,
    )


def _controllability(
    cfg: PipelineConfig, root: Path, split: str, scenes: int | None, seed: int, starts_per_scene: int = 2
) -> DatasetConfig:
    """A controllability set (K action sequences from each start) in the scenes of `split`."""
    control = ControllabilityConfig(
        repo_id=f"local/{root.name}",
        root=str(root),
        families=cfg.families,
        split=split,
        max_scenes=scenes,
        starts_per_scene=starts_per_scene,
        seed=seed,
        image_size=cfg.image_size,
        workers=cfg.workers,
        overwrite=True,
    )
    run_once(root, control, cfg.fresh, lambda: collect_controllability(control))
    return DatasetConfig(repo_id=control.repo_id, root=control.root)


def demonstrations(cfg: PipelineConfig, out: Path) -> Datasets:
    """Planner demonstrations in the IND scenes, a recorded ManiSkill trajectory file converted to a LeRobotDataset
    and, at the scales with held-out scenes, a held-out collection in OOD scenes, a validation collection in IND
    scenes and a controllability set from OOD starts."""
    train = _collect(
        CollectConfig(
            repo_id=DEMOS_REPO_ID,
            root=str(out / DEMOS_DIR),
            families=cfg.families,
            split="ind",
            max_scenes=cfg.scenes,
            episodes_per_scene=cfg.episodes_per_scene,
            image_size=cfg.image_size,
            workers=cfg.workers,
            keep_failed=True,
            segmentation=True,
        ),
        cfg.fresh,
    )
    record = {
        "family": cfg.families[0],
        "scene": select_scenes("ind")[0].id,
        "image_size": cfg.image_size,
        "seed": HELDOUT_SEED,
    }
    converted = out / CONVERTED_DIR
    h5_dir = out / TRAJECTORIES_DIR
    if not is_done(converted, record, cfg.fresh):
        start(h5_dir)
        h5 = record_maniskill_trajectories(
            h5_dir, record["family"], record["scene"], episodes=1, image_size=cfg.image_size, seed=HELDOUT_SEED
        )
        start(converted)
        convert(ConvertConfig(h5=str(h5), root=str(converted), repo_id="local/maniskill_converted", overwrite=True))
        mark_done(converted, record)
    h5 = next(h5_dir.glob("*.h5"))
    heldout = DatasetConfig(repo_id="local/maniskill_converted", root=str(converted))
    validation, controllability, controllability_ind = train, None, None
    if cfg.heldout_scenes:
        heldout = _unseen_episodes(cfg, out / HELDOUT_DIR, "ood", cfg.heldout_scenes, 4, HELDOUT_SEED)
        validation = _unseen_episodes(cfg, out / VALIDATION_DIR, "ind", cfg.scenes, 1, VALIDATION_SEED)
        controllability = _controllability(cfg, out / CONTROL_DIR, "ood", cfg.heldout_scenes, CONTROL_SEED)
        # One start per training scene, from new initial states: where RL runs, the world model is judged first.
        controllability_ind = _controllability(cfg, out / CONTROL_IND_DIR, "ind", cfg.scenes, CONTROL_IND_SEED, 1)
    exploration = None
    if cfg.explore_episodes_per_scene:
        exploration = _collect(
            CollectConfig(
                repo_id="local/roboscape_explore",
                root=str(out / EXPLORE_DIR),
                families=cfg.families,
                split="ind",
                max_scenes=cfg.scenes,
                episodes_per_scene=cfg.explore_episodes_per_scene,
                kinds=list(EXPLORATORY_KINDS),
                seed=EXPLORE_SEED,
                image_size=cfg.image_size,
                workers=cfg.workers,
                keep_failed=True,
            ),
            cfg.fresh,
        )
    return Datasets(train, heldout, validation, controllability, h5, exploration, controllability_ind)


# ---- models ------------------------------------------------------------------------------------------------------


def tokenizer(cfg: PipelineConfig, out: Path, data: Datasets) -> Path:
    """Train the image tokenizer, measured on the held-out episodes as it trains; returns its pretrained_model
    directory."""
    folder = out / TOKENIZER_DIR
    train = TrainTokenizerConfig(
        dataset=data.train,
        heldout=data.heldout,
        tokenizer=TokenizerConfig.get_choice_class(cfg.tokenizer_preset)(image_size=cfg.image_size),
        train=TokenizerTrainingConfig(
            steps=cfg.tokenizer_steps,
            batch_size=cfg.tokenizer_batch_size,
            save_freq=max(cfg.tokenizer_steps // 4, 1),
            eval_freq=max(cfg.tokenizer_steps // 10, 1),
        ),
        output_dir=folder,
        num_workers=min(cfg.workers, 2),
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
    # The tokenizer's own stage record (its settings and the seconds of its run) names the model measured.
    settings = {"report": report_cfg, "tokenizer": json.loads((out / TOKENIZER_DIR / STAGE_FILE).read_text())}
    run_once(folder, settings, cfg.fresh, lambda: evaluate_tokenizer(report_cfg))
    return json.loads((folder / "tokenizer_report.json").read_text())


def world_models(cfg: PipelineConfig, out: Path, data: Datasets, tokenizer_path: Path) -> dict[str, Path]:
    """Train the action and the text world models (each with its done head); returns {control: directory}. The
    action model also trains on the exploratory episodes, and reads its retrieval and action gain on the
    controllability set as it trains."""
    return {
        control: _world_model(cfg, out / world_model_dir(control), data, tokenizer_path, control, steps)
        for control, steps in (("action", cfg.wm_steps), ("text", cfg.text_wm_steps))
    }


def ensemble_members(cfg: PipelineConfig, out: Path, data: Datasets, tokenizer_path: Path, n: int) -> list[Path]:
    """`n` more action world models, trained as the run's own but from other seeds (1..n): an ensemble whose
    disagreement guards PPO in the world model (envs/ensemble.py)."""
    folders = [out / world_model_dir(f"action_seed{seed}") for seed in range(1, n + 1)]
    return [
        _world_model(cfg, folder, data, tokenizer_path, "action", cfg.wm_steps, seed)
        for seed, folder in enumerate(folders, start=1)
    ]


def _world_model(
    cfg: PipelineConfig, folder: Path, data: Datasets, tokenizer_path: Path, control: str, steps: int, seed: int = 0
) -> Path:
    action = control == "action"
    train = TrainWorldModelConfig(
        dataset=data.train,
        tokenizer=str(tokenizer_path),
        wm=WorldModelConfig.get_choice_class(cfg.wm_preset)(control=control),
        train=WorldModelTrainingConfig(
            steps=steps,
            batch_size=cfg.wm_batch_size,
            save_freq=max(steps // 4, 1),
            eval_freq=max(steps // 10, 1),
            seed=seed,
        ),
        output_dir=folder,
        cache_dir=folder.parent / TOKEN_CACHE_DIR,
        exploration=data.exploration if action else None,
        exploration_share=cfg.exploration_share,
        heldout_control=data.controllability if action else None,
        device=cfg.device,
    )
    return _train(folder, train, train_world_model, cfg.fresh)


def _train(folder: Path, train, trainer, fresh: bool) -> Path:
    """Run `trainer` on its config `train` into `folder` unless done, resuming a killed run of the same settings
    from its checkpoints; returns the final model."""
    train_once(folder, train, fresh, lambda resume: trainer(replace(train, train=replace(train.train, resume=resume))))
    return folder / FINAL


def reward_models(
    cfg: PipelineConfig, out: Path, data: Datasets, tokenizer_path: Path, models: dict[str, Path]
) -> dict[str, Path]:
    """Train the paper's baseline rewards (embedding-based and proxy-based) and the success classifier; {} when
    reward_model_steps is 0."""
    trained = {}
    for kind in (*REWARD_BASELINES, SUCCESS_CLASSIFIER) if cfg.reward_model_steps else ():
        folder = out / reward_model_dir(kind)
        train = TrainRewardConfig(
            reward=RewardModelConfig(kind=kind),
            dataset=data.train,
            tokenizer=str(tokenizer_path),
            action_world_model=str(models["action"]),
            # The embedding head reads clips of the action model's window; the image networks single frames.
            train=RewardTrainingConfig(steps=cfg.reward_model_steps, batch_size=8 if kind == "embedding" else 32),
            output_dir=folder,
            cache_dir=out / TOKEN_CACHE_DIR,
            device=cfg.device,
        )
        run_once(folder, train, cfg.fresh, lambda t=train: train_reward_model(t))
        trained[kind] = folder / FINAL
    return trained


def done_report(
    cfg: PipelineConfig, out: Path, data: Datasets, tokenizer_path: Path, models: dict[str, Path], trained: dict
) -> dict:
    """Which done signal the env trusts (the action model's head or the success classifier) and its threshold,
    chosen on the validation episodes and measured on the held-out ones; returns the report."""
    folder = out / DONE_REPORT_DIR
    classifier = trained.get(SUCCESS_CLASSIFIER)
    report_cfg = DoneReportConfig(
        dataset=spread(data.heldout, cfg.report_episodes),
        validation=data.validation,
        tokenizer=str(tokenizer_path),
        world_model=str(models["action"]),
        success_classifier=_str(classifier),
        output_dir=folder,
        device=cfg.device,
    )
    run_once(folder, report_cfg, cfg.fresh, lambda: evaluate_done(report_cfg))
    return json.loads((folder / "done_report.json").read_text())


def world_model_env(
    cfg: PipelineConfig,
    data: Datasets,
    tokenizer_path: Path,
    models: dict[str, Path],
    done: dict | None = None,
    trained: dict | None = None,
) -> RoboscapeWorldModelEnvConfig:
    """The `roboscape_wm` env of these models, starting from the demonstrations' first frames; with a done report,
    its chosen done source and threshold (for success, the goal and the sparse reward)."""
    chosen = dict(done_source="world_model")
    if done is not None:
        source, theta = done["chosen"]["source"], done["chosen"]["theta"]
        classifier = (trained or {}).get(SUCCESS_CLASSIFIER) if source == "classifier" else None
        chosen = dict(done_source=source, success_classifier=_str(classifier), theta=theta, theta_sps=theta)
    return RoboscapeWorldModelEnvConfig(
        dataset_repo_id=data.train.repo_id,
        dataset_root=data.train.root,
        tokenizer=str(tokenizer_path),
        action_world_model=str(models["action"]),
        text_world_model=str(models["text"]),
        families=cfg.families,
        image_size=cfg.image_size,
        max_goal_steps=cfg.max_goal_steps,
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
    cfg: PipelineConfig, out: Path, data: Datasets, tokenizer_path: Path, models: dict[str, Path], domain: str = "ood"
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
        dataset=spread(episodes, cfg.report_episodes),
        tokenizer=str(tokenizer_path),
        world_model=str(models["action"]),
        output_dir=folder,
        max_episodes=cfg.report_episodes,
        controllability=control,
        allow_random_lpips=True,
        device=cfg.device,
    )
    run_once(folder, report_cfg, cfg.fresh, lambda: evaluate_fidelity(report_cfg))
    return json.loads((folder / "fidelity.json").read_text())


def reward_report(
    cfg: PipelineConfig, out: Path, data: Datasets, env: RoboscapeWorldModelEnvConfig, baselines: dict[str, Path]
) -> dict:
    """Every reward along the held-out episodes and how well its return separates success from failure."""
    folder = out / REWARD_REPORT_DIR
    report_cfg = RewardReportConfig(
        env=env,
        dataset=spread(data.heldout, cfg.report_episodes),
        embedding_reward=_str(baselines.get("embedding")),
        proxy_reward=_str(baselines.get("proxy")),
        output_dir=folder,
        max_episodes=cfg.report_episodes,
    )
    # The report points a copy of the env at the held-out data, every episode of it (a converted dataset records
    # no task family to filter by).
    run_once(
        folder, report_cfg, cfg.fresh, lambda: write_reward_report(replace(report_cfg, env=replace(env, families=[])))
    )
    return json.loads((folder / "reward_report.json").read_text())


def _str(path: Path | None) -> str | None:
    return None if path is None else str(path)


def world_model_rollout(out: Path, env_cfg: RoboscapeWorldModelEnvConfig, episodes: int = 2, steps: int = 40) -> dict:
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
    return {
        "video": video,
        "plot": plot,
        "steps": len(rewards),
        "episodes": episodes,
        "returns": [round(float(r), 2) for r in rewards.sum(0)],
    }
