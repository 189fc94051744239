import json

import h5py
import numpy as np
import pytest
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from lerobot_roboscape.dataset.convert import ConvertConfig, convert
from tests.conftest import record_maniskill_file


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    return record_maniskill_file(tmp_path_factory.mktemp("ms_rgb"))


def _source(h5_path):
    meta = json.loads(h5_path.with_suffix(".json").read_text())
    with h5py.File(h5_path) as f:
        return [
            (f[f"traj_{e['episode_id']}/actions"][:], f[f"traj_{e['episode_id']}/success"][:]) for e in meta["episodes"]
        ]


def test_every_episode_and_frame_arrives(recorded, tmp_path):
    root = tmp_path / "converted"
    convert(ConvertConfig(h5=str(recorded), root=str(root), task="pick up the cube"))
    ds = LeRobotDataset("local/maniskill_converted", root=root)
    source = _source(recorded)
    assert ds.meta.total_episodes == len(source)
    assert ds.meta.total_frames == sum(len(a) for a, _ in source)
    actions = np.array(ds.hf_dataset["action"])
    success = np.array(ds.hf_dataset["next.success"]).reshape(-1)
    assert np.allclose(actions, np.concatenate([a for a, _ in source]))
    assert (success == np.concatenate([s for _, s in source])).all()
    assert "observation.images.third_view" not in ds.features  # PickCube's camera keeps its own name
    assert ds[0]["observation.images.base_camera"].shape[-2:] == (32, 32)
    assert ds[0]["task"] == "pick up the cube"


def test_missing_json_is_named(recorded, tmp_path):
    lonely = tmp_path / "lonely.h5"
    lonely.write_bytes(recorded.read_bytes())
    with pytest.raises(FileNotFoundError, match="lonely.json"):
        convert(ConvertConfig(h5=str(lonely), root=str(tmp_path / "out")))
    assert not (tmp_path / "out").exists()


def test_truncated_h5_is_named_and_leaves_nothing(recorded, tmp_path):
    cut = tmp_path / "cut.h5"
    cut.write_bytes(recorded.read_bytes()[: recorded.stat().st_size // 2])
    (tmp_path / "cut.json").write_text(recorded.with_suffix(".json").read_text())
    with pytest.raises(ValueError, match="cut.h5"):
        convert(ConvertConfig(h5=str(cut), root=str(tmp_path / "out")))
    assert not (tmp_path / "out").exists()
    assert not any(p.name.startswith(".out.partial") for p in tmp_path.iterdir())


def test_wrong_shapes_name_the_episode(recorded, tmp_path):
    bad = tmp_path / "bad.h5"
    bad.write_bytes(recorded.read_bytes())
    (tmp_path / "bad.json").write_text(recorded.with_suffix(".json").read_text())
    with h5py.File(bad, "a") as f:
        del f["traj_1/success"]
        f["traj_1/success"] = np.zeros(2, dtype=bool)
    with pytest.raises(ValueError, match=r"bad.h5 episode 1: 'success' has 2"):
        convert(ConvertConfig(h5=str(bad), root=str(tmp_path / "out")))
    assert not (tmp_path / "out").exists()


def test_state_only_file_says_how_to_render(tmp_path):
    h5 = record_maniskill_file(tmp_path, obs_mode="state", episodes=1, steps=3)
    with pytest.raises(ValueError, match="replay_trajectory"):
        convert(ConvertConfig(h5=str(h5), root=str(tmp_path / "out")))


def test_existing_output_is_kept(recorded, tmp_path):
    (tmp_path / "out").mkdir()
    with pytest.raises(FileExistsError, match="out"):
        convert(ConvertConfig(h5=str(recorded), root=str(tmp_path / "out")))


@pytest.mark.slow  # records in the simulator and runs ManiSkill's replay command, as the slow fixtures do
def test_file_rendered_by_replay_trajectory_converts(tmp_path):
    """The route the state-only error suggests: ManiSkill's replay_trajectory renders RGB, then we convert."""
    import subprocess
    import sys

    h5 = record_maniskill_file(tmp_path, obs_mode="state", episodes=1, steps=4)
    subprocess.run(
        [
            sys.executable,
            "-m",
            "mani_skill.trajectory.replay_trajectory",
            "--traj-path",
            str(h5),
            "--obs-mode",
            "rgb",
            "--save-traj",
            "--use-env-states",
            "--allow-failure",
        ],
        check=True,
        capture_output=True,
        timeout=300,
    )
    rendered = next(tmp_path.glob("traj.rgb.*.h5"))
    ds = convert(ConvertConfig(h5=str(rendered), root=str(tmp_path / "out"), task="pick up the cube"))
    ((actions, success),) = _source(h5)
    assert ds.meta.total_frames == len(actions)
    assert np.allclose(np.array(ds.hf_dataset["action"]), actions, atol=1e-6)
