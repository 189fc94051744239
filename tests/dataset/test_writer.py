import time

import numpy as np

from lerobot_roboscape.dataset.episode import Episode
from lerobot_roboscape.dataset.reader import open_dataset, read_frames
from lerobot_roboscape.dataset.writer import write_dataset


def test_no_frame_is_dropped_when_the_video_encoder_falls_behind(tmp_path, monkeypatch):
    """LeRobot's streaming encoder drops frames once its queue stays full; a written episode keeps every frame."""
    from lerobot.datasets import compute_stats

    update = compute_stats.RunningQuantileStats.update
    stalled = []

    def slow_update(self, *args, **kwargs):  # the encoder thread stalls once, as under a loaded CPU
        if not stalled:
            stalled.append(True)
            time.sleep(1.0)
        return update(self, *args, **kwargs)

    monkeypatch.setattr(compute_stats.RunningQuantileStats, "update", slow_update)
    n = 60
    frames = np.zeros((n, 32, 32, 3), np.uint8)
    frames[:, :, :, 0] = np.linspace(0, 250, n).astype(np.uint8)[:, None, None]  # each frame its own red level
    episode = Episode(
        images={"wrist": frames},
        state=np.zeros((n, 2), np.float32),
        action=np.zeros((n, 7), np.float32),
        reward=np.zeros(n, np.float32),
        success=np.zeros(n, bool),
        done=np.eye(n, dtype=bool)[-1],
        task="push the red cube forward",
    )
    root = tmp_path / "ds"
    write_dataset([episode], "local/writer", root, fps=20, state_names=["a", "b"])
    last = read_frames(open_dataset("local/writer", str(root)), 0, [-1])["wrist"][0]
    assert abs(int(last[..., 0].mean()) - 250) <= 6
