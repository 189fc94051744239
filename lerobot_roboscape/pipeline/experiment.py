"""The paper's claim (Table 1), measured on the models a pipeline run already trained: PPO from the SFT checkpoint
in the world model, in the simulator in one scene and in every training scene, at equal wall-clock; the reward
ablation; the simulator success of PPO's checkpoints along its run; world-model rollouts beside the same actions
replayed in the simulator; Table 1 with 95% intervals of the differences; and the report.

Its inputs are the stages before PPO in `output_dir`, as `roboscape-demo` writes them: the demonstrations, the
tokenizer, both world models and the done report (and the SFT checkpoint, unless one is given). Each step skips
what a run with the same settings completed, so a killed run resumes.
"""

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

from lerobot.configs.default import DatasetConfig

from lerobot_roboscape.checkpoints import FINAL
from lerobot_roboscape.errors import MissingInputError
from lerobot_roboscape.pipeline import stages
from lerobot_roboscape.pipeline.config import PipelineConfig

logger = logging.getLogger(__name__)


@dataclass
class ExperimentConfig:
    """Args:
    pipeline: the run (`--pipeline.scale`, `--pipeline.output_dir` holding the trained stages, PPO's and the
        table's sizes: `--pipeline.ppo_minutes`, `--pipeline.table_episodes`, ...).
    sft_checkpoint: the SFT'd policy PPO starts from (a pretrained_model directory); null: SFT with lerobot-train
        on `sft_dataset_root` (or the run's demonstrations).
    sft_dataset_repo_id: demonstrations SFT imitates, when it runs.
    sft_dataset_root: their local root (null: the run's demonstrations).
    curve_episodes: simulator episodes per family (OOD) behind each point of the curve of PPO's checkpoints.
    replay_episodes: world-model rollouts of the policy after PPO in the world model replayed in the simulator.
    report_dir: where the report (report.md, results.json, figures, videos) goes.
    """

    pipeline: PipelineConfig = field(default_factory=lambda: PipelineConfig(scale="bench", output_dir="outputs/bench"))
    sft_checkpoint: str | None = None
    sft_dataset_repo_id: str = "local/roboscape_sft_demos"
    sft_dataset_root: str | None = None
    curve_episodes: int = 10
    replay_episodes: int = 8
    report_dir: str = "docs/results/bench"


@dataclass
class TrainedStages:
    """What the experiment reads from the run's output_dir."""

    data: stages.Datasets
    tokenizer: Path
    models: dict[str, Path]
    done: dict
    reward_models: dict[str, Path]


def trained_stages(cfg: PipelineConfig, out: Path) -> TrainedStages:
    """The demonstrations, tokenizer, world models, done report and reward models of the run in `out`."""
    train = DatasetConfig(repo_id="local/roboscape_demos", root=str(out / stages.DEMOS_DIR))
    tokenizer = out / stages.TOKENIZER_DIR / FINAL
    models = {control: out / stages.world_model_dir(control) / FINAL for control in ("action", "text")}
    done = out / stages.DONE_REPORT_DIR / "done_report.json"
    for path in (Path(train.root) / "meta" / "info.json", tokenizer, *models.values(), done):
        if not path.exists():
            raise MissingInputError(
                f"{path} is missing: the experiment runs on a pipeline run's trained stages; run roboscape-demo "
                f"--scale={cfg.scale} --output_dir={out} first"
            )
    reward_models = {
        kind: out / stages.reward_model_dir(kind) / FINAL
        for kind in (*stages.REWARD_BASELINES, stages.SUCCESS_CLASSIFIER)
        if (out / stages.reward_model_dir(kind) / FINAL).exists()
    }
    data = stages.Datasets(train, train, train, None, Path())
    return TrainedStages(data, tokenizer, models, json.loads(done.read_text()), reward_models)


def sft_policy(cfg: ExperimentConfig, out: Path, data: stages.Datasets) -> dict[str, Path]:
    """{policy: SFT checkpoint}: the one given, or lerobot-train's on the SFT demonstrations."""
    if cfg.sft_checkpoint:
        return {"roboscape_mlp": Path(cfg.sft_checkpoint).resolve()}
    dataset = data.train
    if cfg.sft_dataset_root:
        dataset = DatasetConfig(repo_id=cfg.sft_dataset_repo_id, root=str(Path(cfg.sft_dataset_root).resolve()))
    return stages.sft(cfg.pipeline, out, stages.Datasets(dataset, dataset, dataset, None, Path()))


def run_experiment(cfg: ExperimentConfig) -> Path:
    """Run every step (skipping those complete); returns the report."""
    p, out = cfg.pipeline, Path(cfg.pipeline.output_dir).resolve()
    trained = trained_stages(p, out)
    wm_env = stages.world_model_env(p, trained.data, trained.tokenizer, trained.models, trained.done, trained.reward_models)
    sft = sft_policy(cfg, out, trained.data)
    rl = stages.rl(p, out, trained.data, wm_env, sft)
    return rl
