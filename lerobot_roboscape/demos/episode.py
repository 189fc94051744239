from dataclasses import dataclass, field

import numpy as np


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
    """

    images: dict[str, np.ndarray]
    state: np.ndarray
    action: np.ndarray
    reward: np.ndarray
    success: np.ndarray
    done: np.ndarray
    task: str
    info: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.action)

    @property
    def succeeded(self) -> bool:
        return bool(self.success[-1]) if len(self.success) else False

    def validate(self, where: str) -> None:
        """Raise ValueError naming `where` (file and episode) if arrays disagree in length or dtype."""
        n = len(self.action)
        if n == 0:
            raise ValueError(f"{where}: episode has no frames")
        arrays = {"state": self.state, "reward": self.reward, "success": self.success, "done": self.done}
        arrays.update({f"images.{k}": v for k, v in self.images.items()})
        for key, value in arrays.items():
            if len(value) != n:
                raise ValueError(f"{where}: {key} has {len(value)} frames but action has {n}")
        for name, img in self.images.items():
            if img.ndim != 4 or img.shape[-1] != 3 or img.dtype != np.uint8:
                raise ValueError(f"{where}: camera {name!r} must be (T, H, W, 3) uint8, got {img.shape} {img.dtype}")
