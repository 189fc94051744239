import time

import numpy as np
import pytest
from lerobot.datasets import compute_stats
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from lerobot_roboscape.dataset.episode import Episode
from lerobot_roboscape.dataset.reader import open_dataset, read_frames
from lerobot_roboscape.dataset.writer import write_dataset
from roboscape_core.errors import InvalidInputError
from tests.dataset import still_episode


def stall_encoder_once(monkeypatch):
    """The encoder thread stalls for a second on its first frame, as under a loaded CPU."""
    update = compute_stats.RunningQuantileStats.update
    stalled = []

    def slow_update(self, *args, **kwargs):
        if not stalled:
            stalled.append(True)
            time.sleep(1.0)
        return update(self, *args, **kwargs)

    monkeypatch.setattr(compute_stats.RunningQuantileStats, "update", slow_update)


def graded_episode(n: int = 60) -> Episode:
    frames = np.zeros((n, 32, 32, 3), np.uint8)
    frames[:, :, :, 0] = np.linspace(0, 250, n).astype(np.uint8)[:, None, None]  # each frame its own red level
    return still_episode({"wrist": frames})


def test_no_frame_is_dropped_when_the_video_encoder_falls_behind(tmp_path, monkeypatch):
    """LeRobot's streaming encoder drops frames once its queue stays full; a written episode keeps every frame."""
    stall_encoder_once(monkeypatch)
    root = tmp_path / "ds"
    write_dataset([graded_episode()], "local/writer", root, fps=20, state_names=["a", "b"])
    last = read_frames(open_dataset("local/writer", str(root)), 0, [-1])["wrist"][0]
    assert abs(int(last[..., 0].mean()) - 250) <= 6


def test_a_video_short_of_its_frames_is_named_and_nothing_lands(tmp_path, monkeypatch):
    """Should frames still go missing (LeRobot's bounded queue forced back), the writer names the video and the
    episodes it holds, and leaves no dataset behind."""
    stall_encoder_once(monkeypatch)
    create = LeRobotDataset.create
    monkeypatch.setattr(
        LeRobotDataset, "create", lambda *args, **kwargs: create(*args, **(kwargs | {"encoder_queue_maxsize": 1}))
    )
    root = tmp_path / "ds"
    with pytest.raises(
        InvalidInputError, match=r"wrist/chunk-000/file-000.mp4: \d+ frames, 60 expected \(episodes 0-0\)"
    ):
        write_dataset([graded_episode()], "local/writer", root, fps=20, state_names=["a", "b"])
    assert not root.exists()


def test_episodes_spread_over_video_files_read_back_at_their_frames(tmp_path):
    """Past `video_file_mb` a camera's next episode starts a new file (here: a file per episode); every episode
    still reads back its own first and last frames, and the frame check counts each file."""
    root = tmp_path / "ds"
    dataset = write_dataset(
        [graded_episode(), graded_episode(40), graded_episode()],
        "local/writer",
        root,
        fps=20,
        state_names=["a", "b"],
        video_file_mb=1e-6,
    )
    assert len(list((root / "videos").rglob("*.mp4"))) == 3
    for episode in range(3):
        first, last = read_frames(dataset, episode, [0, -1])["wrist"]
        assert int(first[..., 0].mean()) <= 6
        assert abs(int(last[..., 0].mean()) - 250) <= 6


def test_joining_episodes_videos_leaves_the_console_to_the_progress_bars(tmp_path, capfd):
    """LeRobot joins each new episode's video onto the camera's file; libav's muxer would say so on stderr."""
    write_dataset([graded_episode(), graded_episode()], "local/writer", tmp_path / "ds", fps=20, state_names=["a", "b"])
    assert "[mp4 @" not in capfd.readouterr().err
