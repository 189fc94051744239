import json
import subprocess
import sys

import pytest

from tests.conftest import IMAGE_SIZE, lerobot_train, roboscape_wm_args

pytestmark = pytest.mark.slow  # the simulator, or commands in subprocesses


def test_lerobot_eval_runs_a_lerobot_policy_in_the_simulator_env(act_checkpoint, tmp_path):
    """No discovery flag: LeRobot finds the env type through the lerobot_env_roboscape distribution."""
    cmd = [
        sys.executable,
        "-m",
        "lerobot.scripts.lerobot_eval",
        f"--policy.path={act_checkpoint}",
        "--policy.device=cpu",
        "--env.type=roboscape_maniskill",
        f"--env.image_size={IMAGE_SIZE}",
        "--env.include_state=true",
        "--env.families=[push]",
        "--env.episode_length=3",
        "--eval.n_episodes=2",
        "--eval.batch_size=2",
        f"--output_dir={tmp_path}",
    ]
    result = subprocess.run(cmd, capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, result.stderr[-3000:]
    info = json.loads((tmp_path / "eval_info.json").read_text())
    successes = [s for task in info["per_task"] for s in task["metrics"]["successes"]]
    assert info["overall"]["n_episodes"] == len(successes) == 2
    # lerobot-eval's success is the env's is_success, episode by episode
    assert info["overall"]["pc_success"] == pytest.approx(100 * sum(successes) / 2)


def test_lerobot_train_evaluates_the_mlp_in_the_world_model_env(
    demo_dataset, trained_tokenizer, world_models, tmp_path
):
    """lerobot-train's periodic evaluation runs in roboscape_wm: the MLP executes 4-action chunks, and the env steps
    its world model once per chunk (k = 4) and writes the episode's video."""
    _, root = demo_dataset
    lerobot_train(
        root,
        tmp_path / "train",
        2,
        "--policy.type=roboscape_mlp",
        "--policy.hidden_dim=32",
        "--policy.image_feature_dim=32",
        "--env_eval_freq=2",
        *roboscape_wm_args(root, trained_tokenizer, world_models),
        "--eval.n_episodes=1",
        "--eval.batch_size=1",
    )
    assert json.loads((world_models["action"] / "config.json").read_text())["frame_skip"] == 4
    assert len(list((tmp_path / "train" / "eval" / "videos_step_000002").rglob("*.mp4"))) == 1
