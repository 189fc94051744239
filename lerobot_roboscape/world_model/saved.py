"""What a saved world model must carry to be used: the statistics its state channel and its actions are read
with. A model saved before them is refused at load with the command that trains it again."""

import json
from pathlib import Path

from lerobot_roboscape.training.loop import TRAIN_CONFIG
from roboscape_core.errors import InvalidInputError


def retrain_command(model_dir: Path, control: str) -> str:
    """The roboscape-train-wm command that trains a model again, from its run's record (the folder above the saved
    model) where there is one."""
    record = model_dir.parent / TRAIN_CONFIG
    run = json.loads(record.read_text()) if record.is_file() else {}
    dataset = run.get("dataset") or {}
    return (
        f"roboscape-train-wm --dataset.repo_id={dataset.get('repo_id', '<repo id>')} "
        f"--dataset.root={dataset.get('root', '<dataset folder>')} --tokenizer={run.get('tokenizer', '<tokenizer>')} "
        f"--wm.type=<preset> --wm.control={control} --output_dir={model_dir.parent}"
    )


def refuse_unusable(model, model_id: str, root: Path) -> None:
    """Raise where the loaded `model` (from `model_id`, its files in `root`) lacks the statistics it reads with."""
    if model.config.state and model.config.state_mean is None:
        raise InvalidInputError(
            f"{model_id}: a world model saved without the robot's state statistics (before the state was a "
            f"channel of every frame); retrain it: {retrain_command(root, model.config.control)}"
        )
    if model.config.control == "action" and model.config.action_mean is None:
        zeros, ones = [0.0] * model.config.action_dim, [1.0] * model.config.action_dim
        raise InvalidInputError(
            f"{model_id}: an action world model saved without action statistics (before actions were "
            "normalised); retrain it with roboscape-train-wm, or keep its raw-action behaviour by adding "
            f'"action_mean": {zeros}, "action_std": {ones} to its config.json'
        )
