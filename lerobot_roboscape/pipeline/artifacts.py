"""The pipeline's artifacts, each with its kind, and a loader per kind to check that an artifact loads as what it
is said to be."""

import json
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum
from pathlib import Path

import av
import h5py
import imageio.v3 as iio
from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

from lerobot_roboscape.hub.pull import pull_world_models
from lerobot_roboscape.rl.policy_loading import load_policy
from lerobot_roboscape.tokenizer.modeling_tokenizer import VisualTokenizer
from lerobot_roboscape.world_model.modeling_world_model import STWorldModel
from roboscape_core.errors import InvalidInputError, MissingInputError


class ArtifactKind(Enum):
    VIDEO = "video"
    IMAGE = "image"
    JSON = "JSON file"
    MARKDOWN = "markdown file"
    TRAJECTORY_FILE = "ManiSkill trajectory file"
    DATASET = "LeRobotDataset"
    WORLD_MODELS_BUNDLE = "world-models repo"
    POLICY = "LeRobot policy checkpoint"
    WORLD_MODEL = "world model"
    TOKENIZER = "tokenizer"


@dataclass(frozen=True)
class Artifact:
    kind: ArtifactKind
    path: Path


class Artifacts(dict[str, Artifact]):
    """What a run made, by name, in the order made. A name is given once: a second artifact under it would hide the
    first from the run's closing check."""

    def add(self, name: str, kind: ArtifactKind, path: Path | str) -> None:
        if name in self:
            raise ValueError(f"artifact {name!r} is already listed (at {self[name].path})")
        self[name] = Artifact(kind, Path(path))


def _video(path: Path) -> str:
    with av.open(str(path)) as container:
        return f"video, {sum(1 for _ in container.decode(video=0))} frames"


def _image(path: Path) -> str:
    return f"image {'x'.join(map(str, iio.imread(path).shape[:2]))}"


def _json(path: Path) -> str:
    return f"JSON, {len(json.loads(path.read_text()))} keys"


def _markdown(path: Path) -> str:
    return f"markdown, {len(path.read_text().splitlines())} lines"


def _trajectory_file(path: Path) -> str:
    with h5py.File(path) as f:
        return f"trajectory file, {len(f.keys())} episodes"


def _dataset(path: Path) -> str:
    info = json.loads((path / "meta" / "info.json").read_text())
    meta = LeRobotDatasetMetadata(info.get("repo_id", "local/x"), root=path)
    return f"dataset, {meta.total_episodes} episodes"


def _world_models_bundle(path: Path) -> str:
    bundle = pull_world_models(str(path))
    for model in (bundle.action_world_model, bundle.text_world_model):
        STWorldModel.from_pretrained(str(model))
    VisualTokenizer.from_pretrained(str(bundle.tokenizer))
    return "tokenizer + 2 world models"


def _policy(path: Path) -> str:
    policy, _, _ = load_policy(path, "cpu")
    return f"{policy.config.type} policy"


def _world_model(path: Path) -> str:
    return f"{STWorldModel.from_pretrained(str(path)).config.control} world model"


def _tokenizer(path: Path) -> str:
    VisualTokenizer.from_pretrained(str(path))
    return "tokenizer"


LOADERS: dict[ArtifactKind, Callable[[Path], str]] = {
    ArtifactKind.VIDEO: _video,
    ArtifactKind.IMAGE: _image,
    ArtifactKind.JSON: _json,
    ArtifactKind.MARKDOWN: _markdown,
    ArtifactKind.TRAJECTORY_FILE: _trajectory_file,
    ArtifactKind.DATASET: _dataset,
    ArtifactKind.WORLD_MODELS_BUNDLE: _world_models_bundle,
    ArtifactKind.POLICY: _policy,
    ArtifactKind.WORLD_MODEL: _world_model,
    ArtifactKind.TOKENIZER: _tokenizer,
}


def load_artifact(artifact: Artifact) -> str:
    """Load the artifact as its kind; returns what was loaded. Raises MissingInputError when its path is not there,
    InvalidInputError when it does not load as its kind."""
    path, kind = Path(artifact.path), artifact.kind
    if not path.exists():
        raise MissingInputError(f"no {kind.value} at {path}: the path does not exist")
    try:
        return LOADERS[kind](path)
    except Exception as error:
        raise InvalidInputError(f"{path} does not load as a {kind.value} ({type(error).__name__}: {error})") from error
