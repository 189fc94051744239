import json
import subprocess
import sys

import pytest

from tests.conftest import IMAGE_SIZE

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
    assert info["overall"]["n_episodes"] == 2 and 0 <= info["overall"]["pc_success"] <= 100
