"""What a run records beside its checkpoints, for the reports to read: one line of metrics per iteration
(history.jsonl) and videos of episodes."""

import json
from pathlib import Path

import numpy as np

HISTORY = "history.jsonl"


class History:
    """output_dir/history.jsonl: one line of metrics per iteration, for curves without TensorBoard. A resumed run
    drops the lines past its checkpoint, which it trains again."""

    def __init__(self, path: Path, start_iteration: int):
        self.path = path
        kept = []
        if path.is_file():
            kept = [
                line
                for line in path.read_text().splitlines()
                if line and json.loads(line)["iteration"] <= start_iteration
            ]
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text("".join(line + "\n" for line in kept))

    def append(self, row: dict) -> None:
        with self.path.open("a") as f:
            f.write(json.dumps(row) + "\n")


def read_history(output_dir: Path) -> list[dict]:
    path = Path(output_dir) / HISTORY
    return [json.loads(line) for line in path.read_text().splitlines() if line] if path.is_file() else []


def write_video(path: Path, frames: list[np.ndarray], fps: int) -> None:
    import imageio.v3 as iio

    path.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(path, np.stack(frames), plugin="pyav", codec="libx264", fps=fps)
