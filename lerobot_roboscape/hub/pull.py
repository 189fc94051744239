"""Artifacts from the Hugging Face Hub by repo id, or from a local directory shaped like the repo.

With HF_HUB_OFFLINE=1 everything comes from the local cache; an artifact that is not there is an error naming the
repo and the command that makes or fetches it.
"""

import json
from dataclasses import dataclass
from pathlib import Path

from huggingface_hub import constants, snapshot_download
from huggingface_hub.errors import HfHubHTTPError, LocalEntryNotFoundError, RepositoryNotFoundError

from lerobot_roboscape.io.weights import looks_like_repo_id
from roboscape_core.errors import MissingInputError

WORLD_MODELS_MANIFEST = "roboscape_wm.json"


class ArtifactNotFoundError(MissingInputError):
    pass


def snapshot(ref: str, what: str, how_to_make: str, repo_type: str = "model") -> Path:
    """The local directory of `ref`: the directory itself, or the Hub repo's snapshot in the cache."""
    if not looks_like_repo_id(ref):
        path = Path(ref).expanduser()
        if not path.is_dir():
            raise ArtifactNotFoundError(f"no {what} at {ref}: the directory does not exist; {how_to_make}")
        return path
    try:
        return Path(snapshot_download(ref, repo_type=repo_type))
    except LocalEntryNotFoundError as error:
        if constants.HF_HUB_OFFLINE:
            raise ArtifactNotFoundError(
                f"the {what} {ref!r} is not in the Hugging Face cache ({constants.HF_HUB_CACHE}) and HF_HUB_OFFLINE=1: "
                f"download it once online (`hf download {ref}{' --repo-type dataset' * (repo_type == 'dataset')}`), "
                f"or {how_to_make}"
            ) from error
        raise ArtifactNotFoundError(f"the {what} {ref!r} could not be downloaded ({error}); {how_to_make}") from error
    except RepositoryNotFoundError as error:
        raise ArtifactNotFoundError(
            f"there is no {repo_type} repo {ref!r} on the Hub for the {what} (or it is "
            f"private and you are not logged in); {how_to_make}"
        ) from error
    except HfHubHTTPError as error:
        raise ArtifactNotFoundError(f"the {what} {ref!r} could not be downloaded ({error}); {how_to_make}") from error


@dataclass(frozen=True)
class WorldModelBundle:
    """Local paths of a world-models repo made by `roboscape-push --artifact=world_models`."""

    root: Path
    tokenizer: Path
    action_world_model: Path
    text_world_model: Path
    dataset_repo_id: str


def pull_world_models(ref: str) -> WorldModelBundle:
    root = snapshot(
        ref,
        "world models",
        "push them with `roboscape-push --artifact=world_models` (the demo writes a local copy under outputs/demo/hub)",
    )
    manifest = root / WORLD_MODELS_MANIFEST
    if not manifest.is_file():
        raise ArtifactNotFoundError(
            f"{ref} is not a world-models repo of lerobot-roboscape ({WORLD_MODELS_MANIFEST} "
            "is missing); give the tokenizer and world models one by one instead"
        )
    info = json.loads(manifest.read_text())
    paths = {key: root / info[key] for key in ("tokenizer", "action_world_model", "text_world_model")}
    for key, path in paths.items():
        if not (path / "config.json").is_file():
            raise ArtifactNotFoundError(f"{ref}: {info[key]}/config.json of the {key} is missing")
    return WorldModelBundle(root=root, dataset_repo_id=info["dataset_repo_id"], **paths)
