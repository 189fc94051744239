import numpy as np
import pytest
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from lerobot_roboscape.cli.collect import CollectConfig, collect, make_jobs
from lerobot_roboscape.dataset import read_episode_info


def test_collected_dataset_loads_with_lerobot(demo_dataset):
    _, root = demo_dataset
    ds = LeRobotDataset("test/demos", root=root)
    assert ds.meta.total_episodes == 4
    for key in ["observation.images.third_view", "observation.images.wrist", "observation.state", "action",
                "next.reward", "next.done", "next.success"]:
        assert key in ds.features
    item = ds[0]
    assert tuple(item["observation.images.wrist"].shape) == (3, 32, 32)
    assert tuple(item["action"].shape) == (7,)
    assert item["task"] in {"pick up the red cube and place it in the plate", "push the red cube forward"}
    # Exactly one done per episode, on its last frame.
    done = np.array(ds.hf_dataset["next.done"]).reshape(-1)
    episode = np.array(ds.hf_dataset["episode_index"])
    for e in range(4):
        assert done[episode == e].tolist() == [False] * (int((episode == e).sum()) - 1) + [True]


def test_episode_facts_recorded_with_dataset(demo_dataset):
    ds, root = demo_dataset
    info = read_episode_info(root)
    assert [r["episode_index"] for r in info] == [0, 1, 2, 3]
    assert {r["task_family"] for r in info} == {"pick_place", "push"}
    assert {r["optimal"] for r in info} == {True, False}
    assert all(r["split"] == "ind" and r["scene"] == "red_cube-plate-wooden" for r in info)
    lengths = [ds.meta.episodes[i]["length"] for i in range(4)]
    assert lengths == [r["length"] for r in info]
    successes = np.array(ds.hf_dataset["next.success"]).reshape(-1)
    ends = np.cumsum(lengths) - 1
    assert [bool(successes[i]) for i in ends] == [r["success"] for r in info]


def test_job_mix_follows_flags():
    cfg = CollectConfig(families=["pull"], split="ood", max_scenes=3, episodes_per_scene=4, suboptimal_fraction=0.25)
    jobs = make_jobs(cfg)
    assert len(jobs) == 12 and sum(not j.optimal for j in jobs) == 3
    assert len({j.seed for j in jobs}) == 12


def test_existing_output_directory_is_refused(demo_dataset, tmp_path):
    target = tmp_path / "taken"
    target.mkdir()
    (target / "keep.txt").write_text("user data")
    cfg = CollectConfig(root=str(target), families=["push"], max_scenes=1, episodes_per_scene=1, workers=0)
    with pytest.raises(FileExistsError, match="taken"):
        collect(cfg)
    assert (target / "keep.txt").read_text() == "user data"


def test_bad_flags_are_named():
    with pytest.raises(ValueError, match="fly"):
        CollectConfig(families=["fly"])
    with pytest.raises(ValueError, match="1.5"):
        CollectConfig(suboptimal_fraction=1.5)


def test_lerobot_train_accepts_dataset(act_checkpoint):
    assert (act_checkpoint / "model.safetensors").exists()  # the fixture is a real lerobot-train run
