"""Every long command, SIGKILLed inside its work and rerun, ends where an uninterrupted run ends, bit for bit; a
kill never leaves an output that a later run accepts. (World-model training and PPO in `roboscape_wm` are killed
in tests/world_model/test_training.py and tests/rl/test_ppo_world_model.py.)"""

import json

import draccus
import numpy as np
import pyarrow.parquet as pq
import pytest
from lerobot.configs.default import DatasetConfig
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from lerobot_roboscape.dataset.convert import ConvertConfig, convert
from lerobot_roboscape.dataset.reader import episode_indices, read_episode
from lerobot_roboscape.dataset.writer import EPISODES_SIDECAR
from lerobot_roboscape.demos import controllability
from lerobot_roboscape.demos.collect import JOBS, CollectConfig, collect, episodes_dir
from lerobot_roboscape.demos.controllability import ControllabilityConfig, collect_controllability, run_start
from lerobot_roboscape.evaluation.success_rate import EvalConfig, evaluate_success
from lerobot_roboscape.pipeline import data_stages
from lerobot_roboscape.reward.train import TrainRewardConfig, train_reward_model
from lerobot_roboscape.rl.configuration_ppo import PPOConfig
from lerobot_roboscape.rl.ppo import train_ppo
from lerobot_roboscape.tokenizer.token_cache import open_token_cache
from lerobot_roboscape.tokenizer.train import TrainTokenizerConfig, train_tokenizer
from lerobot_roboscape.training.checkpoints import FINAL, last_checkpoint
from lerobot_roboscape.training.loop import read_curve
from lerobot_roboscape.world_model.train import prepare_token_cache
from roboscape_core.errors import InvalidInputError, OutputExistsError
from tests.conftest import IMAGE_SIZE, TEST_WM_ARGS, record_maniskill_file
from tests.harness import assert_same_weights, command, kill_when, rerun

pytestmark = pytest.mark.slow  # the simulator, or commands in subprocesses


def assert_same_dataset(expected, got) -> None:
    """Same tables (every column of every frame), metadata, episode facts and decoded frames."""
    tables = sorted(p.relative_to(expected) for p in expected.rglob("*.parquet"))
    assert tables == sorted(p.relative_to(got) for p in got.rglob("*.parquet"))
    for table in tables:
        assert pq.read_table(expected / table).equals(pq.read_table(got / table)), table
    for meta in ("meta/info.json", EPISODES_SIDECAR):
        assert (expected / meta).read_text() == (got / meta).read_text(), meta
    a, b = LeRobotDataset("test/a", root=expected), LeRobotDataset("test/b", root=got)
    for index in episode_indices(a):
        frames_a, frames_b = read_episode(a, index).images, read_episode(b, index).images
        assert all(np.array_equal(frames_a[camera], frames_b[camera]) for camera in frames_a), f"episode {index}"


def test_collect(tmp_path):
    args = [
        "--repo_id=test/demos",
        "--families=[push]",
        "--max_scenes=1",
        "--episodes_per_scene=2",
        "--failed_fraction=0.5",
        f"--image_size={IMAGE_SIZE}",
        "--workers=0",
        "--seed=11",
    ]
    collect(draccus.parse(CollectConfig, args=[*args, f"--root={tmp_path / 'reference'}"]))
    root, work = tmp_path / "demos", tmp_path / ".demos.episodes"
    kill_when(command("collect", *args, f"--root={root}"), lambda: any(work.glob("*.npz")))
    assert not root.exists() and len(list(work.glob("*.npz"))) == 1
    with pytest.raises(OutputExistsError, match="--resume=true"):  # a plain rerun neither starts over nor resumes
        collect(draccus.parse(CollectConfig, args=[*args, f"--root={root}"]))
    rerun("collect", *args, f"--root={root}", "--resume=true")
    assert not work.exists()
    assert_same_dataset(tmp_path / "reference", root)


def test_collect_control(tmp_path, monkeypatch):
    args = [
        "--repo_id=test/control",
        "--families=[push]",
        "--split=ind",
        "--max_scenes=1",
        "--starts_per_scene=2",
        "--sequences=2",
        "--steps=4",
        f"--image_size={IMAGE_SIZE}",
        "--workers=0",
    ]
    collect_controllability(draccus.parse(ControllabilityConfig, args=[*args, f"--root={tmp_path / 'reference'}"]))
    root, work = tmp_path / "control", tmp_path / ".control.episodes"
    # killed once the first start's sequences are saved: the rerun runs the second start only
    kill_when(command("collect_control", *args, f"--root={root}"), lambda: len(list(work.glob("*.npz"))) >= 2)
    assert not root.exists() and sorted(f.name for f in work.glob("*.npz"))[:2] == ["000000-0.npz", "000000-1.npz"]
    with pytest.raises(OutputExistsError, match="--resume=true"):
        collect_controllability(draccus.parse(ControllabilityConfig, args=[*args, f"--root={root}"]))
    run = []
    monkeypatch.setattr(controllability, "run_start", lambda task: run.append(task.start) or run_start(task))
    rerun("collect_control", *args, f"--root={root}", "--resume=true")
    assert run == [1]
    assert not work.exists()
    assert_same_dataset(tmp_path / "reference", root)


def test_a_pipeline_rerun_continues_a_killed_collection_and_fresh_discards_it(tmp_path):
    cfg = CollectConfig(
        repo_id="test/demos",
        root=str(tmp_path / "demos"),
        families=["push"],
        max_scenes=1,
        episodes_per_scene=1,
        image_size=IMAGE_SIZE,
        workers=0,
    )
    work = episodes_dir(cfg.root)
    work.mkdir()
    (work / JOBS).write_text("[]")  # an interrupted collection of another plan
    with pytest.raises(InvalidInputError, match="collected with other settings"):  # resumed, not refused
        data_stages._collect(cfg, fresh=False)
    data_stages._collect(cfg, fresh=True)
    assert not work.exists() and LeRobotDataset("test/demos", root=cfg.root).num_episodes == 1


def test_convert(tmp_path):
    h5 = record_maniskill_file(tmp_path / "source")
    root = tmp_path / "converted"
    args = [f"--h5={h5}", f"--root={root}", "--task=pick up the cube"]
    kill_when(command("convert", *args), lambda: any(tmp_path.glob(".converted.partial-*/converted/meta")))
    assert not root.exists()  # nothing, not a partial dataset
    rerun("convert", *args)
    assert not any(tmp_path.glob(".converted.partial-*"))  # the killed run's leftovers are gone
    convert(ConvertConfig(h5=str(h5), root=str(tmp_path / "reference"), task="pick up the cube"))
    assert_same_dataset(tmp_path / "reference", root)


@pytest.mark.parametrize("trainer", ["tokenizer", "reward"])
def test_training(trainer, demo_dataset, trained_tokenizer, token_cache, world_models, tmp_path):
    _, root = demo_dataset
    common = [
        "--dataset.repo_id=test/demos",
        f"--dataset.root={root}",
        "--train.steps=24",
        "--train.save_freq=4",
        "--train.log_freq=4",
        "--train.mixed_precision=no",
    ]
    if trainer == "tokenizer":
        name, config, train = "train_tokenizer", TrainTokenizerConfig, train_tokenizer
        args = [
            *common,
            f"--tokenizer.image_size={IMAGE_SIZE}",
            "--tokenizer.base_channels=8",
            "--tokenizer.channel_multipliers=[1,2,2,2]",
            "--tokenizer.codebook_bits=6",
            "--tokenizer.object_weight=2",
            "--heldout.repo_id=test/demos",
            f"--heldout.root={root}",
            "--heldout.episodes=[3]",
            "--train.eval_freq=4",
            "--train.batch_size=4",
            "--num_workers=0",
            "--allow_random_lpips=true",
        ]
    else:
        name, config, train = "train_reward", TrainRewardConfig, train_reward_model
        args = [
            *common,
            "--reward.kind=embedding",
            f"--tokenizer={trained_tokenizer}",
            f"--action_world_model={world_models['action']}",
            f"--token_cache={token_cache.root}",
            "--train.batch_size=4",
        ]
    train(draccus.parse(config, args=[*args, f"--output_dir={tmp_path / 'reference'}"]))
    killed = tmp_path / "killed"
    kill_when(command(name, *args, f"--output_dir={killed}"), lambda: last_checkpoint(killed) is not None)
    assert not (killed / FINAL).exists()
    rerun(name, *args, f"--output_dir={killed}", "--train.resume=true")
    assert_same_weights(tmp_path / "reference" / FINAL / "model.safetensors", killed / FINAL / "model.safetensors")
    if trainer == "tokenizer":  # the held-out curve has each point once, as the uninterrupted run's
        drop_seconds = lambda curve: [{k: v for k, v in p.items() if k != "seconds"} for p in curve]  # noqa: E731
        assert [p["step"] for p in read_curve(killed)] == list(range(4, 25, 4))
        assert drop_seconds(read_curve(killed)) == drop_seconds(read_curve(tmp_path / "reference"))


def test_ppo_in_the_simulator(mlp_checkpoint, tmp_path):
    args = [
        f"--policy_path={mlp_checkpoint}",
        "--env.type=roboscape_maniskill",
        f"--env.image_size={IMAGE_SIZE}",
        "--env.families=[push]",
        "--env.episode_length=3",
        "--num_envs=1",
        "--iterations=2",
        "--save_freq=1",
        "--critic_warmup_iterations=1",
        "--minibatch_size=3",
        "--device=cpu",
        "--mixed_precision=no",
        "--seed=7",
    ]
    reference = train_ppo(draccus.parse(PPOConfig, args=[*args, f"--output_dir={tmp_path / 'reference'}"]))
    killed = tmp_path / "killed"
    kill_when(command("ppo", *args, f"--output_dir={killed}"), lambda: (killed / "checkpoints" / "last").is_file())
    assert not (killed / "checkpoints" / "00000002").exists()
    rerun("ppo", *args, f"--output_dir={killed}", "--resume=true")
    resumed = killed / "checkpoints" / "00000002"
    assert_same_weights(reference / "model.safetensors", resumed / FINAL / "model.safetensors")
    state = "training_state/iteration.json"
    assert (last_checkpoint(reference.parent) / state).read_text() == (resumed / state).read_text()


def test_eval(mlp_checkpoint, tmp_path):
    args = [
        f"--policy_path={mlp_checkpoint}",
        "--families=[push]",
        "--episodes=1",
        "--batch_size=1",
        "--episode_length=2",
        "--device=cpu",
        "--videos=1",
    ]
    reference = evaluate_success(draccus.parse(EvalConfig, args=[*args, f"--output_dir={tmp_path / 'reference'}"]))
    for split in ("ind", "ood"):
        cells = reference["splits"][split]
        assert cells["push"]["episodes"] == cells["all"]["episodes"] == 1
        outcome = "success" if cells["push"]["successes"] else "failure"
        assert (tmp_path / "reference" / "videos" / split / f"00_push_{outcome}.mp4").exists()
    assert "| OOD | push |" in (tmp_path / "reference" / "eval.md").read_text()

    killed = tmp_path / "killed"
    kill_when(command("evaluate", *args, f"--output_dir={killed}"), lambda: (killed / "splits" / "ind.json").exists())
    assert not (killed / "eval.json").exists()  # no table reported as complete
    with pytest.raises(OutputExistsError, match="--resume=true"):
        evaluate_success(draccus.parse(EvalConfig, args=[*args, f"--output_dir={killed}"]))
    rerun("evaluate", *args, f"--output_dir={killed}", "--resume=true")
    assert json.loads((killed / "eval.json").read_text()) == reference


def test_token_cache(demo_dataset, trained_tokenizer, token_cache, tmp_path):
    _, root = demo_dataset
    cache_dir = tmp_path / "cache"
    args = [
        "--dataset.repo_id=test/demos",
        f"--dataset.root={root}",
        f"--tokenizer={trained_tokenizer}",
        f"--cache_dir={cache_dir}",
        f"--output_dir={tmp_path / 'wm'}",
        "--train.steps=1",
        *TEST_WM_ARGS,
    ]
    kill_when(command("train_wm", *args), lambda: any(cache_dir.glob(".v*")))  # killed while tokenizing
    assert not [p for p in cache_dir.iterdir() if not p.name.startswith(".")]  # no cache a later run would open
    rebuilt, _ = prepare_token_cache(
        DatasetConfig(repo_id="test/demos", root=str(root)), str(trained_tokenizer), cache_dir
    )
    assert [p.name for p in cache_dir.iterdir()] == [rebuilt.root.name]  # the killed build's leftovers are gone
    rebuilt = open_token_cache(rebuilt.root)
    assert np.array_equal(rebuilt.tokens, token_cache.tokens) and np.array_equal(rebuilt.actions, token_cache.actions)
