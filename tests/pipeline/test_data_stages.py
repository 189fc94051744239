import shutil

import numpy as np
import pytest
from lerobot.configs.default import DatasetConfig

from lerobot_roboscape.dataset.writer import write_dataset
from lerobot_roboscape.pipeline.data_stages import whole_dataset
from roboscape_core.errors import InvalidInputError
from tests.dataset import still_episode

VIDEO = "videos/observation.images.wrist/chunk-000/file-000.mp4"


def test_a_dataset_found_with_frames_missing_is_named(tmp_path):
    """A dataset an older writer left short of frames is refused where a run would have taken it as complete."""
    frames = np.zeros((12, 32, 32, 3), np.uint8)
    for name, n in (("whole", 12), ("short", 11)):
        write_dataset([still_episode({"wrist": frames[:n]})], f"local/{name}", tmp_path / name, fps=20)
    assert whole_dataset(DatasetConfig(repo_id="local/whole", root=str(tmp_path / "whole"))).repo_id == "local/whole"
    shutil.copy(tmp_path / "short" / VIDEO, tmp_path / "whole" / VIDEO)  # what a dropped frame leaves
    with pytest.raises(InvalidInputError, match=rf"whole: videos short .*{VIDEO}: 11 frames, 12 expected"):
        whole_dataset(DatasetConfig(repo_id="local/whole", root=str(tmp_path / "whole")))
