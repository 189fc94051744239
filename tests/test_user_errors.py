"""Bad input to a command gives one line on stderr that names what to fix, exit status 2 and no partial output;
the traceback only with ROBOSCAPE_DEBUG=1. A bug keeps its traceback."""

import errno
import json
import os
import re
import shutil

import draccus
import h5py
import numpy as np
import pytest
import torch
from safetensors.torch import load_file, save_file

from lerobot_roboscape.cli import DEBUG_ENV, USER_ERROR_EXIT, one_line_errors
from lerobot_roboscape.cli import collect as collect_cli
from lerobot_roboscape.cli import convert as convert_cli
from lerobot_roboscape.cli import demo as demo_cli
from lerobot_roboscape.cli import eval_agreement as agreement_cli
from lerobot_roboscape.cli import eval_done as eval_done_cli
from lerobot_roboscape.cli import evaluate as evaluate_cli
from lerobot_roboscape.cli import experiment as experiment_cli
from lerobot_roboscape.cli import ppo as ppo_cli
from lerobot_roboscape.cli import reward_report as reward_report_cli
from lerobot_roboscape.cli import train_reward as train_reward_cli
from lerobot_roboscape.cli import train_tokenizer as train_tokenizer_cli
from lerobot_roboscape.cli import train_wm as train_wm_cli
from lerobot_roboscape.dataset.reader import open_dataset
from lerobot_roboscape.reward.baselines import RewardModel, RewardModelConfig
from lerobot_roboscape.rl.policy_loading import load_policy
from lerobot_roboscape.tokenizer.token_cache import open_token_cache
from lerobot_roboscape.world_model.modeling_world_model import STWorldModel
from roboscape_core.errors import InvalidInputError
from tests.conftest import record_maniskill_file


def one_line(capsys, main, argv) -> str:
    """Run a command's main; it must exit with the user-error status, its error in one line (after any progress
    bars) and no traceback. Returns that line."""
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == USER_ERROR_EXIT
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    last = err.strip().splitlines()[-1]
    assert ": error: " in last.split("\r")[-1], err
    return last.split("\r")[-1]


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    return record_maniskill_file(tmp_path_factory.mktemp("ms"))


def copy_of(recorded, folder, name="bad"):
    folder.mkdir(parents=True, exist_ok=True)
    h5 = folder / f"{name}.h5"
    shutil.copy(recorded, h5)
    shutil.copy(recorded.with_suffix(".json"), h5.with_suffix(".json"))
    return h5


@pytest.mark.parametrize(
    ("argv", "expected"),
    [
        (["--failed_fraction=2"], "roboscape-collect: error: failed_fraction must be in [0, 1], got 2"),
        (["--episodes_per_scene=abc"], "`episodes_per_scene`: Couldn't parse 'abc' into an int"),
        (["--families=[fly]"], "Unknown task families ['fly']"),
        (["--split=moon"], "Unknown split 'moon'"),
    ],
)
def test_bad_flag_values(capsys, argv, expected):
    assert expected in one_line(capsys, collect_cli.main, argv)


# Each command refuses a bad flag value before it does any work, naming the flag and what it accepts.
BAD_FLAGS = {
    "experiment: unknown scale": (experiment_cli, ["--pipeline.scale=huge"], "--scale must be one of"),
    "experiment: no replayed rollout": (
        experiment_cli,
        ["--replay_episodes=0"],
        "--replay_episodes must be >= 1, got 0",
    ),
    "experiment: on a run that was never made": (
        experiment_cli,
        ["--pipeline.scale=smoke", "--pipeline.output_dir=nowhere/run"],
        "is missing: the experiment runs on a pipeline run's trained stages; run roboscape-demo --scale=smoke",
    ),
    "demo: unknown family": (demo_cli, ["--data.families=[fly]"], "unknown task families ['fly']"),
    "demo: a flag from before the stages' settings were nested": (
        demo_cli,
        ["--scale=bench", "--wm_steps=10"],
        "--wm_steps is now --wm_train.steps",
    ),
    "experiment: a flag from before the nesting": (
        experiment_cli,
        ["--pipeline.ppo_minutes=6"],
        "--pipeline.ppo_minutes is now --pipeline.ppo.time_budget_s (in seconds)",
    ),
    "demo: cameras and tokenizer at different sizes": (
        demo_cli,
        ["--data.image_size=128"],
        "--tokenizer.image_size=64 differs from the cameras' --data.image_size=128: set both",
    ),
    "demo: stop after no stage": (demo_cli, ["--stop_after=tokeniser"], "stop_after='tokeniser' is not a stage"),
    "agreement: no policy": (agreement_cli, [], "--policy_paths is required"),
    "agreement: unknown split": (agreement_cli, ["--policy_paths=[p]", "--split=moon"], "got 'moon'"),
    "agreement: unknown family": (agreement_cli, ["--policy_paths=[p]", "--families=[fly]"], "['fly']"),
    "agreement: goals the simulator cannot give": (
        agreement_cli,
        ["--policy_paths=[p]", "--env.text_world_model=t", "--env.goal_source=dataset_last_frame"],
        "use --env.goal_source=text_model",
    ),
    "env: done threshold above 1": (
        agreement_cli,
        ["--policy_paths=[p]", "--env.text_world_model=t", "--env.theta=1.5"],
        "theta and theta_sps must be in (0, 1], got 1.5",
    ),
    "env: unknown similarity": (
        agreement_cli,
        ["--policy_paths=[p]", "--env.text_world_model=t", "--env.similarity=cosine"],
        "similarity must be one of ('auto', 'lpips', 'tokenizer', 'pixel'), got 'cosine'",
    ),
    "env: classifier done without a classifier": (
        agreement_cli,
        ["--policy_paths=[p]", "--env.text_world_model=t", "--env.done_source=classifier"],
        "done_source=classifier needs success_classifier",
    ),
    "env: episodes of no step": (
        agreement_cli,
        ["--policy_paths=[p]", "--env.text_world_model=t", "--env.episode_length=0"],
        "episode_length must be >= 1 or null",
    ),
    "env: unknown precision": (
        agreement_cli,
        ["--policy_paths=[p]", "--env.text_world_model=t", "--env.precision=fp8"],
        "precision must be one of ('auto', 'float32', 'bfloat16'), got 'fp8'",
    ),
    "eval: no policy": (evaluate_cli, [], "--policy_path is required"),
    "eval: unknown split": (evaluate_cli, ["--policy_path=p", "--splits=[moon]"], "got ['moon']"),
    "ppo: no policy": (ppo_cli, [], "--policy_path is required"),
    "ppo: unknown value loss": (ppo_cli, ["--policy_path=p", "--value_loss=l1"], "value_loss must be mse or huber"),
    "reward report: unknown frames": (
        reward_report_cli,
        ["--env.text_world_model=t", "--frames=dreamed"],
        "frames must be one of ('real', 'open_loop'), got 'dreamed'",
    ),
    "reward report: unknown reward type": (
        reward_report_cli,
        ["--env.text_world_model=t", "--env.reward_type=magic"],
        "reward_type must be world_model, embedding or proxy, got 'magic'",
    ),
    "reward report: a baseline reward without its model": (
        reward_report_cli,
        ["--env.text_world_model=t", "--env.reward_type=proxy"],
        "reward_type=proxy needs reward_model",
    ),
    "train reward: unknown kind": (train_reward_cli, ["--reward.kind=magic"], "kind must be one of"),
    "train world model: exploration share above 1": (
        train_wm_cli,
        ["--exploration_share=2"],
        "exploration_share must be in [0, 1], got 2",
    ),
    "eval done: missing tokenizer": (
        eval_done_cli,
        ["--tokenizer=nowhere/tokenizer", "--world_model=x"],
        "no VisualTokenizer at nowhere/tokenizer",
    ),
}


@pytest.mark.parametrize("fault", BAD_FLAGS)
def test_each_command_refuses_bad_flags_by_name(capsys, monkeypatch, fault):
    monkeypatch.setattr("huggingface_hub.constants.HF_HUB_OFFLINE", True)  # a repo id that is not there: no retries
    cli, argv, expected = BAD_FLAGS[fault]
    assert expected in one_line(capsys, cli.main, argv)


def test_convert_refuses_non_finite_actions_and_names_where(capsys, recorded, tmp_path):
    h5 = copy_of(recorded, tmp_path)
    with h5py.File(h5, "a") as f:
        f["traj_1/actions"][3, 2] = np.nan
    line = one_line(capsys, convert_cli.main, [f"--h5={h5}", f"--root={tmp_path / 'out'}"])
    assert f"{h5} episode 1 frame 3: action is not finite" in line
    assert not (tmp_path / "out").exists() and not list(tmp_path.glob(".out.*"))  # nothing partial


@pytest.mark.parametrize("fault", ["no_h5", "no_json", "truncated", "bad_json", "short_success", "state_only"])
def test_convert_refuses_malformed_files(capsys, recorded, tmp_path, fault):
    h5 = copy_of(recorded, tmp_path)
    expected = {
        "no_h5": "no such trajectory file",
        "no_json": "bad.json: missing",
        "truncated": "cannot be read",
        "bad_json": "not a ManiSkill trajectory .json",
        "short_success": "episode 0: 'success' has 2 entries",
        "state_only": "replay_trajectory",
    }[fault]
    if fault == "no_h5":
        h5 = tmp_path / "absent.h5"
    elif fault == "no_json":
        h5.with_suffix(".json").unlink()
    elif fault == "truncated":
        h5.write_bytes(recorded.read_bytes()[:4096])
    elif fault == "bad_json":
        h5.with_suffix(".json").write_text("{not json")
    elif fault == "short_success":
        with h5py.File(h5, "a") as f:
            del f["traj_0/success"]
            f["traj_0/success"] = np.zeros(2, dtype=bool)
    else:
        h5 = record_maniskill_file(tmp_path / "state", obs_mode="state", episodes=1, steps=3)
    assert expected in one_line(capsys, convert_cli.main, [f"--h5={h5}", f"--root={tmp_path / 'out'}"])
    assert not (tmp_path / "out").exists()


def test_datasets_with_non_finite_values_are_refused_where_read(demo_dataset, tmp_path, capsys):
    """A dataset edited after writing (NaN in a parquet cell) is refused by every reader, naming the frame."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    _, root = demo_dataset
    bad = tmp_path / "bad"
    shutil.copytree(root, bad)
    table_path = next((bad / "data").rglob("*.parquet"))
    table = pq.read_table(table_path)
    rewards = table.column("next.reward").to_numpy().copy()
    rewards[7] = np.inf
    pq.write_table(
        table.set_column(table.column_names.index("next.reward"), "next.reward", pa.array(rewards)), table_path
    )
    episode, frame = table.column("episode_index")[7].as_py(), table.column("frame_index")[7].as_py()
    with pytest.raises(InvalidInputError, match=f"episode {episode} frame {frame}: next.reward is not finite"):
        open_dataset("test/bad", bad)
    line = one_line(
        capsys,
        train_tokenizer_cli.main,
        ["--dataset.repo_id=test/bad", f"--dataset.root={bad}", f"--output_dir={tmp_path / 'tok'}"],
    )
    assert "next.reward is not finite" in line and not (tmp_path / "tok").exists()


def test_token_cache_with_non_finite_labels_is_refused(token_cache, tmp_path):
    bad = tmp_path / "cache"
    shutil.copytree(token_cache.root, bad)
    rewards = np.load(bad / "rewards.npy")
    rewards[token_cache.episodes[1]["start"] + 2] = np.nan
    np.save(bad / "rewards.npy", rewards)
    with pytest.raises(
        InvalidInputError,
        match=f"rewards.npy \\(episode {token_cache.episodes[1]['episode_index']} frame 2\\): rewards is not finite",
    ):
        open_token_cache(bad)


def test_missing_models_and_paths_are_named(capsys, demo_dataset, tmp_path):
    _, root = demo_dataset
    line = one_line(
        capsys,
        train_wm_cli.main,
        ["--dataset.repo_id=test/demos", f"--dataset.root={root}", f"--tokenizer={tmp_path / 'no_tokenizer'}"],
    )
    assert f"no VisualTokenizer at {tmp_path / 'no_tokenizer'}: no such directory" in line
    line = one_line(capsys, train_tokenizer_cli.main, ["--dataset.repo_id=test/x", f"--dataset.root={tmp_path}/x"])
    assert f"no LeRobot dataset at {tmp_path}/x" in line
    line = one_line(
        capsys,
        ppo_cli.main,
        [
            f"--policy_path={tmp_path / 'no_policy'}",
            "--env.type=roboscape_maniskill",
            f"--output_dir={tmp_path / 'ppo'}",
        ],
    )
    assert "No LeRobot policy checkpoint at" in line and "no_policy" in line


def test_mismatched_camera_is_named(capsys, mlp_checkpoint, tmp_path):
    line = one_line(
        capsys,
        ppo_cli.main,
        [
            f"--policy_path={mlp_checkpoint}",
            "--env.type=roboscape_maniskill",
            "--env.image_size=48",
            f"--output_dir={tmp_path / 'ppo'}",
        ],
    )
    assert "--env.image_size=32" in line
    assert "unknown task families ['juggle']" in one_line(
        capsys, evaluate_cli.main, ["--policy_path=x", "--families=[juggle]"]
    )


def test_full_disk_and_read_only_output_say_so(capsys, recorded, tmp_path, monkeypatch):
    from lerobot_roboscape.dataset import writer

    h5 = copy_of(recorded, tmp_path)
    for code, words in ((errno.ENOSPC, "the disk is full"), (errno.EROFS, "the file system is read-only")):

        def fail(dataset, episode, code=code):
            raise OSError(code, os.strerror(code), str(dataset.root / "data"))

        monkeypatch.setattr(writer, "_add_episode", fail)
        line = one_line(capsys, convert_cli.main, [f"--h5={h5}", f"--root={tmp_path / 'out'}"])
        assert words in line and ".out.partial-" in line
        assert not (tmp_path / "out").exists() and not list(tmp_path.glob(".out.*"))


def test_weights_that_do_not_fit_their_config_are_refused(world_models, mlp_checkpoint, tmp_path):
    source = world_models["action"]
    tensors = load_file(source / "model.safetensors")
    name = next(iter(tensors))
    cases = {
        "missing": {k: v for k, v in tensors.items() if k != name},
        "shape": {**tensors, name: tensors[name][..., :1].contiguous()},
        "dtype": {**tensors, name: tensors[name].to(torch.float16)},
    }
    expected = {
        "missing": f"missing tensors {name}",
        "shape": f"mismatched tensors {name} ",
        "dtype": f"mismatched tensors {name} {tuple(tensors[name].shape)} F16",
    }
    for case, edited in cases.items():
        bad = tmp_path / case
        shutil.copytree(source, bad)
        save_file(edited, bad / "model.safetensors")
        with pytest.raises(
            InvalidInputError, match=re.escape(str(bad / "model.safetensors")) + ".*" + re.escape(expected[case])
        ):
            STWorldModel.from_pretrained(bad)
    pickled = tmp_path / "pickled"
    pickled.mkdir()
    RewardModel(RewardModelConfig(kind="embedding", d_model=8)).save_pretrained(pickled)
    (pickled / "model.safetensors").unlink()
    torch.save({}, pickled / "pytorch_model.bin")
    with pytest.raises(InvalidInputError, match="model.safetensors"):  # never unpickled
        RewardModel.from_pretrained(pickled)

    policy = tmp_path / "policy"
    shutil.copytree(mlp_checkpoint, policy)
    tensors = load_file(policy / "model.safetensors")
    dropped = sorted(tensors)[0]
    save_file({k: v for k, v in tensors.items() if k != dropped}, policy / "model.safetensors")
    with pytest.raises(InvalidInputError, match=f"missing tensors {dropped}"):
        load_policy(policy, "cpu")


def test_debug_switch_shows_the_traceback_and_bugs_keep_theirs(monkeypatch):
    monkeypatch.setenv(DEBUG_ENV, "1")
    with pytest.raises(draccus.utils.ParsingError):
        collect_cli.main(["--failed_fraction=2"])
    monkeypatch.delenv(DEBUG_ENV)

    @one_line_errors("roboscape-bug")
    def buggy(argv):
        return json.loads("{")["key"]  # a JSONDecodeError (a ValueError) raised by our own bug

    with pytest.raises(json.JSONDecodeError):
        buggy([])
