"""Per-frame masks of the task object, the container and the robot, stored beside a LeRobot dataset.

The simulator renders every camera's per-actor segmentation; collection (`--segmentation=true`) keeps only what the
reports need, the task object, the container and the robot's links, as one label image per frame and camera:

    <dataset root>/segmentation/<camera>/episode_<index:06d>.npy    (T, H, W) uint8, frame-aligned with the videos
    <dataset root>/meta/roboscape_segmentation.json                  {"labels": {"0": "background", ...}, ...}

A pixel is labelled with the actor seen there, so an object hidden behind the gripper has no pixels in that frame.
Plain .npy files (no pickle) load with `mmap_mode`, so one frame is read without reading the episode.
"""

import json
from pathlib import Path

import numpy as np

from roboscape_core.errors import InvalidInputError

BACKGROUND, OBJECT, CONTAINER, ROBOT = 0, 1, 2, 3
LABELS = {BACKGROUND: "background", OBJECT: "object", CONTAINER: "container", ROBOT: "robot"}
SEGMENTATION_DIR = "segmentation"
SEGMENTATION_META = "meta/roboscape_segmentation.json"
LAYOUT = f"{SEGMENTATION_DIR}/<camera>/episode_<index:06d>.npy: (T, H, W) uint8 labels, frame-aligned with the videos"


def label_image(
    actor_ids: np.ndarray, object_id: int, container_id: int, robot_ids: tuple[int, ...] = ()
) -> np.ndarray:
    """The simulator's per-actor ids (H, W) -> (H, W) uint8 labels."""
    labels = np.full(actor_ids.shape, BACKGROUND, np.uint8)
    labels[np.isin(actor_ids, robot_ids)] = ROBOT
    labels[actor_ids == container_id] = CONTAINER
    labels[actor_ids == object_id] = OBJECT
    return labels


def mask_path(root: str | Path, camera: str, episode_index: int) -> Path:
    return Path(root) / SEGMENTATION_DIR / camera / f"episode_{episode_index:06d}.npy"


def write_masks(root: str | Path, episode_index: int, masks: dict[str, np.ndarray]) -> None:
    """Write one episode's label images (camera -> (T, H, W) uint8) into a dataset being built at `root` (the
    writer's staging directory, moved into place as a whole)."""
    for camera, labels in masks.items():
        path = mask_path(root, camera, episode_index)
        path.parent.mkdir(parents=True, exist_ok=True)
        np.save(path, labels, allow_pickle=False)
    meta = Path(root) / SEGMENTATION_META
    if not meta.exists():
        meta.write_text(json.dumps({"labels": {str(k): v for k, v in LABELS.items()}, "layout": LAYOUT}, indent=2))


def has_masks(root: str | Path) -> bool:
    return (Path(root) / SEGMENTATION_META).is_file()


def read_masks(root: str | Path, episode_index: int, cameras: list[str], length: int, mmap: bool = False) -> dict:
    """camera -> (T, H, W) uint8 labels of one episode; an `InvalidInputError` naming the file when one is missing
    or does not match the episode's length."""
    masks = {}
    for camera in cameras:
        path = mask_path(root, camera, episode_index)
        if not path.is_file():
            raise InvalidInputError(
                f"{path} is missing: dataset {root} has no segmentation of episode {episode_index}, camera "
                f"{camera!r} (collect with --segmentation=true)"
            )
        labels = np.load(path, mmap_mode="r" if mmap else None, allow_pickle=False)
        if labels.ndim != 3 or len(labels) != length or labels.dtype != np.uint8:
            raise InvalidInputError(
                f"{path}: expected ({length}, H, W) uint8 labels for episode {episode_index}, got "
                f"{labels.shape} {labels.dtype}"
            )
        masks[camera] = labels
    return masks
