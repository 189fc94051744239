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


def test_the_validation_halves_each_hold_every_family_and_outcome(tmp_path):
    """The done threshold is chosen on one half of the validation episodes and judged in domain on the other: each
    half takes every other episode of each (family, outcome), so both see successes and failures of every family."""
    from dataclasses import replace

    from lerobot_roboscape.pipeline.stages import halves

    frames = np.zeros((4, 32, 32, 3), np.uint8)
    outcomes = [("push", False), ("push", True), ("push", True), ("pick_place", False), ("pick_place", True)]
    outcomes += [("push", False), ("pick_place", False), ("pick_place", True), ("push", True)]
    episodes = [
        replace(still_episode({"wrist": frames}), info={"task_family": family, "success": success})
        for family, success in outcomes
    ]
    write_dataset(episodes, "local/validation", tmp_path / "validation", fps=20)
    choose, judge = halves(DatasetConfig(repo_id="local/validation", root=str(tmp_path / "validation")))
    # push failed: 0, 5; push succeeded: 1, 2, 8; pick_place failed: 3, 6; pick_place succeeded: 4, 7
    assert choose.episodes == [0, 1, 3, 4, 8] and judge.episodes == [2, 5, 6, 7]
    assert choose.root == judge.root == str(tmp_path / "validation")
