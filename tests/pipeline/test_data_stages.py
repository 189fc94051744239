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


@pytest.mark.parametrize("starts", [0, 2])
def test_the_ind_controllability_set_is_collected_only_when_asked(tmp_path, monkeypatch, starts):
    """`--data.ind_control_starts=0` collects no IND controllability set (an hour on a CPU that renders slowly, for a
    report the carried models already have); otherwise that many starts per (family, training scene)."""
    from lerobot_roboscape.pipeline import data_stages
    from lerobot_roboscape.pipeline.config import DataConfig
    from lerobot_roboscape.pipeline.layout import CONTROL_IND_DIR, TRAJECTORIES_DIR

    asked = []

    def controllability(data, fresh, root, split, scenes, seed, starts_per_scene=2):
        asked.append((root.relative_to(tmp_path).as_posix(), split, starts_per_scene))
        return DatasetConfig(repo_id=root.name, root=str(root))

    monkeypatch.setattr(data_stages, "_controllability", controllability)
    monkeypatch.setattr(data_stages, "_collect", lambda cfg, fresh: DatasetConfig(repo_id=cfg.repo_id, root=cfg.root))
    monkeypatch.setattr(data_stages, "is_done", lambda *args: True)  # the trajectory file, recorded already
    (tmp_path / TRAJECTORIES_DIR).mkdir()
    (tmp_path / TRAJECTORIES_DIR / "trajectory.h5").touch()
    datasets = data_stages.demonstrations(DataConfig(heldout_scenes=2, ind_control_starts=starts), tmp_path)
    ind = [(CONTROL_IND_DIR, "ind", starts)] if starts else []
    assert [a for a in asked if a[1] == "ind"] == ind and (datasets.controllability_ind is None) == (starts == 0)
    assert datasets.controllability is not None  # the OOD set stays: the world model's training readings
