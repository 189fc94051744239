"""One PPO run as a stage of a run: resumed from its last checkpoint when interrupted, skipped once complete with
the same settings. Apart from the other policy stages, so that a machine without the simulator (where PPO in the
world model runs: pipeline/world_model_runs.py) imports it."""

from dataclasses import replace
from pathlib import Path

from lerobot_roboscape.pipeline.resume import train_once
from lerobot_roboscape.rl.configuration_ppo import PPOConfig
from lerobot_roboscape.rl.ppo import train_ppo
from lerobot_roboscape.training.checkpoints import last_checkpoint, publish_final


def ppo(cfg: PPOConfig, fresh: bool = False) -> Path:
    """One PPO run (resumed from its last checkpoint when interrupted, or when it ran before with a smaller time
    budget: PPO's clock goes on from where it stopped); returns its final checkpoint."""
    folder = Path(cfg.output_dir)
    train_once(
        folder,
        cfg,
        fresh,
        lambda resume: train_ppo(replace(cfg, resume=resume and last_checkpoint(folder) is not None)),
        budgets=("time_budget_s",),
    )
    return publish_final(folder)
