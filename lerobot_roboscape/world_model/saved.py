"""A saved world model: its files (the weights, and a text model's T5 config and tokenizer), and what it must carry
to be used: the statistics its state channel and its actions are read with. A model saved before them is refused at
load with the command that trains it again."""

import json
from pathlib import Path

from huggingface_hub import snapshot_download

from lerobot_roboscape.io.weights import CheckedHubMixin
from lerobot_roboscape.training.loop import TRAIN_CONFIG
from roboscape_core.errors import InvalidInputError

TEXT_ENCODER_DIR = "text_encoder"


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


class SavedWorldModel(CheckedHubMixin):
    """The world model's saving and loading: a text model also saves its T5's config and tokenizer, from which it
    is rebuilt (the weights come with the world model's); a loaded model is refused where it is unusable."""

    def _save_pretrained(self, save_directory: Path) -> None:
        super()._save_pretrained(save_directory)
        if self.config.control == "text":
            self.control_encoder.save_tokenizer_and_config(Path(save_directory) / TEXT_ENCODER_DIR)

    @classmethod
    def _from_pretrained(
        cls,
        *,
        model_id: str,
        revision=None,
        cache_dir=None,
        force_download=False,
        local_files_only=False,
        token=None,
        **kwargs,
    ):
        # A text model rebuilds its T5 from the saved config and tokenizer (weights come with the world model's).
        if Path(model_id).is_dir():
            root = Path(model_id)
        else:
            root = Path(
                snapshot_download(
                    model_id,
                    revision=revision,
                    cache_dir=cache_dir,
                    token=token,
                    local_files_only=local_files_only,
                    allow_patterns=[f"{TEXT_ENCODER_DIR}/*"],
                )
            )
        if (root / TEXT_ENCODER_DIR).is_dir():
            kwargs["text_encoder_dir"] = str(root / TEXT_ENCODER_DIR)
        model = super()._from_pretrained(
            model_id=model_id,
            revision=revision,
            cache_dir=cache_dir,
            force_download=force_download,
            local_files_only=local_files_only,
            token=token,
            **kwargs,
        )
        refuse_unusable(model, model_id, root)
        return model
