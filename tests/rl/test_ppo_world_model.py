"""PPO in `roboscape_wm`, run as a user runs it (the `roboscape-ppo` command): the same flags and seed give the
same bytes, and a run killed with SIGKILL and resumed ends where an uninterrupted one does."""

import os
import signal
import subprocess
import sys
import time

import pytest
import torch
from safetensors.torch import load_file

from tests.conftest import IMAGE_SIZE

ITERATIONS = 3


@pytest.fixture
def ppo_args(demo_dataset, trained_tokenizer, world_models, mlp_checkpoint):
    _, root = demo_dataset
    return [f"--policy_path={mlp_checkpoint}", "--env.type=roboscape_wm", "--env.dataset_repo_id=test/demos",
            f"--env.dataset_root={root}", f"--env.tokenizer={trained_tokenizer}",
            f"--env.action_world_model={world_models['action']}", f"--env.text_world_model={world_models['text']}",
            f"--env.image_size={IMAGE_SIZE}", "--env.episode_length=3", "--env.max_goal_steps=3",
            "--env.similarity=tokenizer", "--env.temperature=1.0", "--num_envs=3", f"--iterations={ITERATIONS}",
            "--save_freq=1", "--critic_warmup_iterations=1", "--minibatch_size=4", "--device=cpu",
            "--mixed_precision=no", "--seed=5"]  # fmt: skip


def command(args: list[str]) -> list[str]:
    return [sys.executable, "-m", "lerobot_roboscape.cli.ppo", *args]


def run(args: list[str]) -> None:
    result = subprocess.run(command(args), capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]


def weights(output_dir, iteration: int = ITERATIONS) -> dict[str, torch.Tensor]:
    return load_file(output_dir / "checkpoints" / f"{iteration:08d}" / "pretrained_model" / "model.safetensors")


def assert_same(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    different = [key for key in a if not torch.equal(a[key], b[key])]
    assert not different, f"tensors differ: {different}"


def test_seeded_runs_are_identical_and_a_killed_run_resumes_exactly(ppo_args, tmp_path):
    run([*ppo_args, f"--output_dir={tmp_path / 'reference'}"])
    reference = weights(tmp_path / "reference")
    assert not all(torch.equal(reference[k], weights(tmp_path / "reference", 1)[k]) for k in reference)  # it trained

    # A second run with the same flags, killed during iteration 2: what it saved before equals the reference.
    killed = tmp_path / "killed"
    process = subprocess.Popen(command([*ppo_args, f"--output_dir={killed}"]), stdout=subprocess.DEVNULL,
                               stderr=subprocess.DEVNULL)  # fmt: skip
    deadline = time.time() + 600
    while not (killed / "checkpoints" / "last").is_file() and process.poll() is None and time.time() < deadline:
        time.sleep(0.05)
    os.kill(process.pid, signal.SIGKILL)
    process.wait()
    assert not (killed / "checkpoints" / f"{ITERATIONS:08d}").exists(), "the run finished before it was killed"
    assert_same(weights(tmp_path / "reference", 1), weights(killed, 1))
    assert (tmp_path / "reference" / "checkpoints" / "00000001" / "training_state" / "iteration.json").read_text() \
        == (killed / "checkpoints" / "00000001" / "training_state" / "iteration.json").read_text()

    run([*ppo_args, f"--output_dir={killed}", "--resume=true"])
    assert_same(reference, weights(killed))
