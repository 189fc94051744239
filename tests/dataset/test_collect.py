import os
import shutil
from collections import Counter

import numpy as np
import pytest
import torch
from lerobot.configs.default import DatasetConfig
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from lerobot_roboscape.dataset.reader import demonstrations_per_scene, successful_episodes
from lerobot_roboscape.dataset.writer import EPISODES_SIDECAR, read_episode_info
from lerobot_roboscape.demos.collect import CollectConfig, collect, make_jobs
from lerobot_roboscape.demos.rollout import run_jobs
from lerobot_roboscape.pipeline.lerobot_cli import sft_episodes
from roboscape_core.errors import InvalidInputError
from tests.conftest import IMAGE_SIZE


def test_collected_dataset_loads_with_lerobot(demo_dataset):
    _, root = demo_dataset
    ds = LeRobotDataset("test/demos", root=root)
    assert ds.meta.total_episodes == 6
    for key in [
        "observation.images.third_view",
        "observation.images.wrist",
        "observation.state",
        "action",
        "next.reward",
        "next.done",
        "next.success",
    ]:
        assert key in ds.features
    item = ds[0]
    assert tuple(item["observation.images.wrist"].shape) == (3, 32, 32)
    assert tuple(item["action"].shape) == (7,)
    assert item["task"] in {"pick up the red cube and place it in the plate", "push the red cube forward"}
    # Exactly one done per episode, on its last frame.
    done = np.array(ds.hf_dataset["next.done"]).reshape(-1)
    episode = np.array(ds.hf_dataset["episode_index"])
    for e in range(6):
        assert done[episode == e].tolist() == [False] * (int((episode == e).sum()) - 1) + [True]


def test_episode_facts_recorded_with_dataset(demo_dataset):
    ds, root = demo_dataset
    info = read_episode_info(root)
    assert [r["episode_index"] for r in info] == list(range(6))
    assert {r["task_family"] for r in info} == {"pick_place", "push"}
    assert [r["kind"] for r in info] == ["optimal", "suboptimal", "failed", "failed", "optimal", "suboptimal"]
    assert all(r["optimal"] == (r["kind"] == "optimal") for r in info)
    assert all(r["split"] == "ind" and r["scene"] == "red_cube-plate-wooden" for r in info)
    lengths = [ds.meta.episodes[i]["length"] for i in range(6)]
    assert lengths == [r["length"] for r in info]
    successes = np.array(ds.hf_dataset["next.success"]).reshape(-1)
    ends = np.cumsum(lengths) - 1
    assert [bool(successes[i]) for i in ends] == [r["success"] for r in info]


def test_job_mix_follows_flags():
    cfg = CollectConfig(
        families=["pull", "push"],
        split="ood",
        max_scenes=3,
        episodes_per_scene=4,
        failed_fraction=0.25,
        suboptimal_fraction=0.5,
    )
    jobs = make_jobs(cfg)
    assert len(jobs) == 24 and len({j.seed for j in jobs}) == 24
    for family in ("pull", "push"):  # dealt per family: 3 of its 12 failed, half of the other 9 suboptimal
        kinds = Counter(j.kind for j in jobs if j.family == family)
        assert kinds == {"failed": 3, "suboptimal": 4, "optimal": 5}
    # A family's few episodes still get their failures (dealt over all its scenes, not per scene).
    few = make_jobs(CollectConfig(families=["push"], max_scenes=2, episodes_per_scene=2, failed_fraction=0.25))
    assert [j.kind for j in few].count("failed") == 1


def process_of(job):
    return job, os.getpid()


def test_one_worker_runs_the_jobs_in_this_process():
    # As the simulator's slots do: a pool of one would only pay a process's start-up (about 12 s of imports).
    for workers in (0, 1):
        assert list(run_jobs([3, 1, 2], workers, process_of)) == [(3, os.getpid()), (1, os.getpid()), (2, os.getpid())]


def threads_of(job):
    return job, os.getpid(), torch.get_num_threads()


@pytest.mark.slow
def test_worker_processes_run_the_jobs_in_order_on_one_torch_thread_each():
    # Two workers with torch's default thread per core fought over 2 cores: 15.5 pick&place episodes/min, 18.7 with one.
    done = list(run_jobs([3, 1, 2, 4], 2, threads_of))
    assert [job for job, _, _ in done] == [3, 1, 2, 4]
    assert {threads for _, _, threads in done} == {1}
    assert os.getpid() not in {pid for _, pid, _ in done}


def test_exploratory_kinds_are_dealt_evenly_and_never_mixed_with_demonstrations():
    jobs = make_jobs(CollectConfig(families=["push"], max_scenes=2, episodes_per_scene=3, kinds=["noisy", "random"]))
    assert Counter(j.kind for j in jobs) == {"noisy": 3, "random": 3}
    with pytest.raises(ValueError, match="mixes exploratory kinds with demonstrations.*dataset of their own"):
        CollectConfig(kinds=["optimal", "random"])
    with pytest.raises(ValueError, match=r"kinds must name plan kinds.*'wander'"):
        CollectConfig(kinds=["wander"])


def test_exploratory_episodes_leave_the_plan(exploration_dataset, demo_dataset):
    """Each kind is recorded with its episode, and each departs from the planner's actions its own way; the
    demonstrations, which SFT and lerobot-train read, hold none of them."""
    explore, root = exploration_dataset
    info = read_episode_info(root)
    kinds = [info[i]["kind"] for i in range(explore.meta.total_episodes)]
    assert Counter(kinds) == {"noisy": 2, "excursion": 2, "random": 2}
    assert not any(facts["optimal"] for facts in info)
    actions = np.asarray(explore.hf_dataset["action"])
    episode = np.asarray(explore.hf_dataset["episode_index"])
    demo, demo_root = demo_dataset
    demo_actions, demo_episode = np.asarray(demo.hf_dataset["action"]), np.asarray(demo.hf_dataset["episode_index"])

    def turning(a):  # share of steps that turn hard about some axis
        return (np.abs(a[:, 3:6]) > 0.5).any(1).mean()

    def gripper_between(a):  # share of steps whose gripper command is neither open nor closed
        return (np.abs(a[:, 6]) < 0.9).mean()

    for i in range(demo.meta.total_episodes):  # the planner barely turns and only opens or closes
        assert turning(demo_actions[demo_episode == i]) < 0.1 and gripper_between(demo_actions[demo_episode == i]) == 0
    for i, kind in enumerate(kinds):
        mine = actions[episode == i]
        if kind == "random":  # stretches over the whole range, the gripper included
            assert turning(mine) > 0.1 and gripper_between(mine) > 0.1
        if kind == "noisy":  # noise on every action, the gripper's too
            assert gripper_between(mine) > 0.2
        if kind in ("excursion", "random"):
            assert info[i]["departures"] >= 1
    assert {facts["kind"] for facts in read_episode_info(demo_root)} <= {"optimal", "suboptimal", "failed"}


@pytest.fixture(scope="module")
def failed_collection(tmp_path_factory):
    """Only planned failures: a given-up pick and place and a missed push (the plan's first random draw picks the
    kind of failure; seeds 1 and 2 draw give up and miss)."""
    root = tmp_path_factory.mktemp("failed") / "demos"
    cfg = CollectConfig(
        repo_id="test/failed",
        root=str(root),
        families=["pick_place", "push"],
        max_scenes=1,
        episodes_per_scene=1,
        failed_fraction=1.0,
        image_size=IMAGE_SIZE,
        workers=1,
        seed=1,
    )
    return collect(cfg), root


def test_planned_failures_fail_in_the_simulator(failed_collection, demo_dataset):
    ds, root = failed_collection
    info = read_episode_info(root)
    assert [(r["task_family"], r["kind"]) for r in info] == [("pick_place", "failed"), ("push", "failed")]
    # The simulator's verdict, on the last frame and on every frame: never accomplished, not even in passing.
    assert [r["success"] for r in info] == [False] * 2
    assert not np.array(ds.hf_dataset["next.success"]).any()
    assert successful_episodes(ds) == []
    with pytest.raises(ValueError, match=str(root)):
        sft_episodes(DatasetConfig(repo_id="test/failed", root=str(root)))

    demos, _ = demo_dataset
    assert successful_episodes(demos) == [r["episode_index"] for r in read_episode_info(demos.root) if r["success"]]
    assert not {2, 3} & set(successful_episodes(demos))  # the fixture's planned failures


def test_sft_takes_the_first_successful_demonstrations_of_each_family_and_scene(demo_dataset):
    demos, root = demo_dataset
    info = read_episode_info(root)
    successful = successful_episodes(demos)
    first = {}
    for r in info:
        if r["success"]:
            first.setdefault((r["task_family"], r["scene"]), r["episode_index"])
    assert demonstrations_per_scene(demos, 1) == sorted(first.values())
    assert len(first) == 2  # one scene, two families
    assert demonstrations_per_scene(demos, None) == demonstrations_per_scene(demos, 3) == successful
    assert sft_episodes(DatasetConfig(repo_id="test/demos", root=str(root)), per_scene=1) == sorted(first.values())
    # The paper's protocol: SFT on the initial scene's demonstrations only.
    (scene,) = {scene for _, scene in first}
    assert demonstrations_per_scene(demos, None, scenes=[scene]) == successful
    assert demonstrations_per_scene(demos, None, scenes=["no_such_scene"]) == []
    with pytest.raises(InvalidInputError, match="no successful episode in scenes \\['no_such_scene'\\]"):
        sft_episodes(DatasetConfig(repo_id="test/demos", root=str(root)), scenes=["no_such_scene"])


def test_successful_episodes_without_facts(demo_dataset, tmp_path):
    demos, root = demo_dataset
    bare = tmp_path / "bare"
    shutil.copytree(root, bare)
    (bare / EPISODES_SIDECAR).unlink()
    assert successful_episodes(LeRobotDataset("test/demos", root=bare)) == successful_episodes(demos)


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
    with pytest.raises(ValueError, match="failed_fraction.*-0.1"):
        CollectConfig(failed_fraction=-0.1)


def test_lerobot_train_accepts_dataset(act_checkpoint):
    assert (act_checkpoint / "model.safetensors").exists()  # the fixture is a real lerobot-train run
