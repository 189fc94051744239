import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from roboscape_core.errors import InvalidInputError, require_finite, require_shape

IMAGES = "images."  # prefix of the camera arrays in a saved episode
MASKS = "masks."  # prefix of the cameras' label images (dataset/segmentation.py), when recorded


@dataclass
class Episode:
    """One demonstration, frame-aligned the LeRobot way: frame t holds the observation before action t and the
    reward/done/success that followed it.

    Args:
        images: camera name -> (T, H, W, 3) uint8.
        state: (T, S) float32 proprioception.
        action: (T, A) float32.
        reward: (T,) float32, success: (T,) bool, done: (T,) bool.
        task: the instruction.
        info: per-episode facts recorded with the dataset (task family, scene, split, optimal, seed, ...).
        masks: camera -> (T, H, W) uint8 labels of the object and the container (dataset/segmentation.py), or None.
    """

    images: dict[str, np.ndarray]
    state: np.ndarray
    action: np.ndarray
    reward: np.ndarray
    success: np.ndarray
    done: np.ndarray
    task: str
    info: dict = field(default_factory=dict)
    masks: dict[str, np.ndarray] | None = None

    def __len__(self) -> int:
        return len(self.action)

    @property
    def succeeded(self) -> bool:
        return bool(self.success[-1]) if len(self.success) else False

    def validate(self, where: str) -> None:
        """Raise InvalidInputError naming `where` (file and episode), the key and the frame if arrays disagree in
        length or dtype, or if a state, action or reward is not finite."""
        n = len(self.action)
        if n == 0:
            raise InvalidInputError(f"{where}: episode has no frames")
        arrays = {"state": self.state, "reward": self.reward, "success": self.success, "done": self.done}
        arrays.update({f"images.{k}": v for k, v in self.images.items()})
        for key, value in arrays.items():
            if len(value) != n:
                raise InvalidInputError(f"{where}: {key} has {len(value)} frames but action has {n}")
        require_shape(self.action, where, "action", (n, None))
        require_shape(self.state, where, "state", (n, None))
        require_shape(self.reward, where, "reward", (n,))
        for key in ("state", "action", "reward"):
            require_finite(getattr(self, key), where, key)
        for name, img in self.images.items():
            if img.ndim != 4 or img.shape[-1] != 3 or img.dtype != np.uint8:
                raise InvalidInputError(
                    f"{where}: camera {name!r} must be (T, H, W, 3) uint8, got {img.shape} {img.dtype}"
                )
        for name, labels in (self.masks or {}).items():
            expected = self.images[name].shape[:3] if name in self.images else None
            if labels.shape != expected or labels.dtype != np.uint8:
                raise InvalidInputError(
                    f"{where}: masks of camera {name!r} must be {expected} uint8 (its images' frames), got "
                    f"{labels.shape} {labels.dtype}"
                )

    def save(self, path: str | Path) -> None:
        """Write to `path` (.npz, no pickled objects), complete or not at all."""
        text = json.dumps({"task": self.task, "info": self.info}).encode()
        arrays = {
            "state": self.state,
            "action": self.action,
            "reward": self.reward,
            "success": self.success,
            "done": self.done,
            **{f"{IMAGES}{k}": v for k, v in self.images.items()},
            **{f"{MASKS}{k}": v for k, v in (self.masks or {}).items()},
            "text": np.frombuffer(text, np.uint8),
        }
        path = Path(path)
        tmp = path.with_name(f".{path.name}.tmp")
        with open(tmp, "wb") as f:
            np.savez_compressed(f, **arrays)
        os.replace(tmp, path)

    @classmethod
    def load(cls, path: str | Path) -> "Episode":
        with np.load(path, allow_pickle=False) as data:
            text = json.loads(data["text"].tobytes())
            images = {k.removeprefix(IMAGES): data[k] for k in data.files if k.startswith(IMAGES)}
            masks = {k.removeprefix(MASKS): data[k] for k in data.files if k.startswith(MASKS)}
            return cls(
                images,
                data["state"],
                data["action"],
                data["reward"],
                data["success"],
                data["done"],
                text["task"],
                text["info"],
                masks or None,
            )
