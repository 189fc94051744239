"""Model and dataset cards, rendered from the Jinja templates in `hub_cards/` as huggingface_hub renders its own."""

import json
from pathlib import Path

from huggingface_hub import DatasetCard, ModelCard
from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata
from lerobot.datasets.utils import create_lerobot_dataset_card
from safetensors import safe_open

from lerobot_roboscape.dataset.writer import read_episode_info
from lerobot_roboscape.io import templates
from roboscape_core.errors import MissingInputError

LICENSE = "apache-2.0"
DATASET_TAGS = ["robotics", "roboscape", "maniskill"]


def templates_dir() -> Path:
    """`hub_cards/` of the source tree, or its copy inside an installed wheel."""
    for candidate in (Path(__file__).parent / "hub_cards", Path(__file__).parents[2] / "hub_cards"):
        if candidate.is_dir():
            return candidate
    raise MissingInputError("the card templates (hub_cards/) are missing from this installation")


def render(template: str, **fields) -> str:
    return templates.render(templates_dir(), template, **fields)


def model_card(template: str, **fields) -> ModelCard:
    """A full card (YAML metadata + text); parsing it checks the metadata before anything is uploaded."""
    return ModelCard(render(template, license=LICENSE, **fields))


def dataset_description(root: Path, repo_id: str) -> str:
    """`hub_cards/dataset.md` filled from the dataset's metadata and per-episode facts."""
    meta = LeRobotDatasetMetadata(repo_id, root=root)
    episodes = read_episode_info(root)
    return render(
        "dataset.md",
        repo_id=repo_id,
        episodes=meta.total_episodes,
        frames=meta.total_frames,
        fps=meta.fps,
        successful=sum(bool(e.get("success")) for e in episodes),
        optimal=sum(bool(e.get("optimal")) for e in episodes),
        families=sorted({e["task_family"] for e in episodes if "task_family" in e}),
        scenes=sorted({e["scene"] for e in episodes if "scene" in e}),
        splits=", ".join(f"{sum(e.get('split') == s for e in episodes)} episodes {s.upper()}" for s in ("ind", "ood")),
        cameras=[key.split(".")[-1] for key in meta.camera_keys],
        image_size=meta.features[meta.camera_keys[0]]["shape"][0] if meta.camera_keys else 0,
    )


def dataset_card(root: Path, repo_id: str) -> DatasetCard:
    """The card LeRobotDataset.push_to_hub uploads: LeRobot's own, with our description and tags."""
    meta = LeRobotDatasetMetadata(repo_id, root=root)
    return create_lerobot_dataset_card(
        tags=DATASET_TAGS,
        dataset_info=meta.info,
        license=LICENSE,
        repo_id=repo_id,
        dataset_description=dataset_description(root, repo_id),
    )


def parameter_count(weights: Path) -> str:
    """Parameters of a safetensors file, read from its header alone, e.g. '1.2M'."""
    with safe_open(weights, framework="pt") as f:
        total = 0
        for key in f.keys():  # safe_open is not a dict
            count = 1
            for dim in f.get_slice(key).get_shape():
                count *= dim
            total += count
    for unit, scale in (("B", 1e9), ("M", 1e6), ("K", 1e3)):
        if total >= scale:
            return f"{total / scale:.1f}{unit}"
    return str(total)


def read_json(path: Path) -> dict:
    return json.loads(path.read_text())
