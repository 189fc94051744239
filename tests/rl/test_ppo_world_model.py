"""PPO in `roboscape_wm`, run as a user runs it (the `roboscape-ppo` command): the same flags and seed give the
same bytes, and a run killed with SIGKILL and resumed ends where an uninterrupted one does."""

from pathlib import Path

import draccus
import pytest
import torch
from safetensors.torch import load_file

from lerobot_roboscape.rl.configuration_ppo import PPOConfig
from lerobot_roboscape.rl.ppo import train_ppo
from tests.conftest import IMAGE_SIZE
from tests.harness import assert_same_weights, command, kill_when, rerun

ITERATIONS = 3


@pytest.fixture
def ppo_args(demo_dataset, trained_tokenizer, world_models, mlp_checkpoint):
    _, root = demo_dataset
    return [
        f"--policy_path={mlp_checkpoint}",
        "--env.type=roboscape_wm",
        "--env.dataset_repo_id=test/demos",
        f"--env.dataset_root={root}",
        f"--env.tokenizer={trained_tokenizer}",
        f"--env.action_world_model={world_models['action']}",
        f"--env.text_world_model={world_models['text']}",
        f"--env.image_size={IMAGE_SIZE}",
        "--env.episode_length=3",
        "--env.max_goal_steps=3",
        "--env.similarity=tokenizer",
        "--env.temperature=1.0",
        "--num_envs=3",
        f"--iterations={ITERATIONS}",
        "--save_freq=1",
        "--critic_warmup_iterations=1",
        "--minibatch_size=4",
        "--device=cpu",
        "--mixed_precision=no",
        "--seed=5",
    ]


def weights(output_dir, iteration: int = ITERATIONS) -> Path:
    return output_dir / "checkpoints" / f"{iteration:08d}" / "pretrained_model" / "model.safetensors"


def test_seeded_runs_are_identical_and_a_killed_run_resumes_exactly(ppo_args, tmp_path):
    reference = tmp_path / "reference"  # trained in this process, the killed run and its resumption in others
    train_ppo(draccus.parse(PPOConfig, args=[*ppo_args, f"--output_dir={reference}"]))
    first, last = load_file(weights(reference, 1)), load_file(weights(reference))
    assert not all(torch.equal(first[k], last[k]) for k in first)  # it trained

    # A second run with the same flags, killed during iteration 2: what it saved before equals the reference.
    killed = tmp_path / "killed"
    kill_when(command("ppo", *ppo_args, f"--output_dir={killed}"), lambda: (killed / "checkpoints" / "last").is_file())
    assert not weights(killed).exists(), "the run finished before it was killed"
    assert_same_weights(weights(reference, 1), weights(killed, 1))
    state = Path("checkpoints", "00000001", "training_state", "iteration.json")
    assert (reference / state).read_text() == (killed / state).read_text()

    rerun("ppo", *ppo_args, f"--output_dir={killed}", "--resume=true")
    assert_same_weights(weights(reference), weights(killed))
