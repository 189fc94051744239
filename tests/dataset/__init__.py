import numpy as np

from lerobot_roboscape.dataset.episode import Episode


def still_episode(images: dict[str, np.ndarray], masks: dict[str, np.ndarray] | None = None) -> Episode:
    """An episode of the given frames (camera -> (n, H, W, 3) uint8) with a still robot, done at its last frame."""
    n = len(next(iter(images.values())))
    return Episode(
        images=images,
        state=np.zeros((n, 2), np.float32),
        action=np.zeros((n, 7), np.float32),
        reward=np.zeros(n, np.float32),
        success=np.zeros(n, bool),
        done=np.eye(n, dtype=bool)[-1],
        task="push the red cube forward",
        masks=masks,
    )
