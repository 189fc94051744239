"""What the claim's experiment reads from a pipeline run: the stages before PPO that `roboscape-demo` trained (the
demonstrations, the tokenizer, both world models, the done report and the reward models)."""

from dataclasses import dataclass
from pathlib import Path

from lerobot.configs.default import DatasetConfig

from lerobot_roboscape.pipeline import layout, methods
from lerobot_roboscape.pipeline.config import PipelineConfig
from lerobot_roboscape.reward.done_report import REPORT_JSON, DoneChoice
from lerobot_roboscape.training.checkpoints import FINAL
from roboscape_core.errors import MissingInputError


@dataclass
class TrainedStages:
    """What the experiment reads from the run's output_dir."""

    demonstrations: DatasetConfig
    tokenizer: Path
    models: layout.WorldModelPaths | None
    done: DoneChoice | None
    reward_models: dict[str, Path]


def trained_stages(cfg: PipelineConfig, out: Path, world_models: bool = True) -> TrainedStages:
    """The demonstrations, tokenizer, world models, done report and reward models of the run in `out` (without
    `world_models`: the demonstrations and the tokenizer alone, for runs in world models trained elsewhere)."""
    train = DatasetConfig(repo_id=layout.DEMOS_REPO_ID, root=str(out / layout.DEMOS_DIR))
    tokenizer = out / layout.TOKENIZER_DIR / FINAL
    models = layout.WorldModelPaths(*(out / layout.world_model_dir(c) / FINAL for c in layout.WorldModelPaths._fields))
    done = out / layout.DONE_REPORT_DIR / REPORT_JSON
    needed = [Path(train.root) / "meta" / "info.json", tokenizer] + ([*models, done] if world_models else [])
    for path in needed:
        if not path.exists():
            stop = "" if world_models else " --stop_after=tokenizer"
            raise MissingInputError(
                f"{path} is missing: the experiment runs on a pipeline run's trained stages; run roboscape-demo "
                f"--scale={cfg.scale} --output_dir={out}{stop} first"
            )
    if not world_models:
        return TrainedStages(train, tokenizer, None, None, {})
    reward_models = {
        kind: out / layout.reward_model_dir(kind) / FINAL
        for kind in (*methods.REWARD_BASELINES, methods.SUCCESS_CLASSIFIER)
        if (out / layout.reward_model_dir(kind) / FINAL).exists()
    }
    return TrainedStages(train, tokenizer, models, DoneChoice.read(done.parent), reward_models)
