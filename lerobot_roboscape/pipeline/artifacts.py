"""Load any artifact of the pipeline by what it is, to check that it loads."""

import json
from pathlib import Path

import av
import h5py
import imageio.v3 as iio
from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

from lerobot_roboscape.hub.pull import WORLD_MODELS_MANIFEST, pull_world_models
from lerobot_roboscape.rl.policy_loading import load_policy
from lerobot_roboscape.tokenizer.modeling_tokenizer import VisualTokenizer
from lerobot_roboscape.world_model.modeling_world_model import STWorldModel


def load_artifact(path: Path) -> str:
    """Load an artifact of the pipeline by what it is; returns what was loaded (raises if it does not load)."""
    path = Path(path)
    if path.suffix == ".mp4":
        with av.open(str(path)) as container:
            return f"video, {sum(1 for _ in container.decode(video=0))} frames"
    if path.suffix == ".png":
        return f"image {'x'.join(map(str, iio.imread(path).shape[:2]))}"
    if path.suffix == ".json":
        return f"JSON, {len(json.loads(path.read_text()))} keys"
    if path.suffix == ".md":
        return f"markdown, {len(path.read_text().splitlines())} lines"
    if path.suffix == ".h5":
        with h5py.File(path) as f:
            return f"trajectory file, {len(f.keys())} episodes"
    if (path / "meta" / "info.json").is_file():
        meta = LeRobotDatasetMetadata(
            json.loads((path / "meta" / "info.json").read_text()).get("repo_id", "local/x"), root=path
        )
        return f"dataset, {meta.total_episodes} episodes"
    if (path / WORLD_MODELS_MANIFEST).is_file():
        bundle = pull_world_models(str(path))
        for model in (bundle.action_world_model, bundle.text_world_model):
            STWorldModel.from_pretrained(str(model))
        VisualTokenizer.from_pretrained(str(bundle.tokenizer))
        return "tokenizer + 2 world models"
    config = json.loads((path / "config.json").read_text())
    if "type" in config:  # a LeRobot policy
        policy, _, _ = load_policy(path, "cpu")
        return f"{config['type']} policy"
    if "control" in config:
        return f"{STWorldModel.from_pretrained(str(path)).config.control} world model"
    VisualTokenizer.from_pretrained(str(path))
    return "tokenizer"
