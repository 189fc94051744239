"""Each policy plugin installs into a clean virtual environment, at the lowest versions its pyproject allows
(uv's lowest-direct resolution: the dependency floors are tested, not trusted), with no ManiSkill, SAPIEN or
lerobot-roboscape, and trains its tiny preset there."""

import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).parents[2]
PLUGINS = {
    "openvla": ROOT / "policies" / "lerobot_policy_openvla",
    "roboscape_mlp": ROOT / "policies" / "lerobot_policy_roboscape_mlp",
}


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("uv") is None, reason="needs uv to build the clean environment")
@pytest.mark.parametrize("plugin", sorted(PLUGINS))
def test_plugin_installs_alone_at_its_floors_and_trains(plugin, tmp_path):
    venv = tmp_path / "venv"
    python = venv / "bin" / "python"
    subprocess.run(["uv", "venv", "--quiet", "--python", sys.executable, str(venv)], check=True)
    # torch as installed here (the same wheel, from uv's cache): its floor is not what this test is about
    torch_pin = f"torch=={torch.__version__.split('+')[0]}"
    subprocess.run(
        ["uv", "pip", "install", "--quiet", "--python", str(python), "--resolution", "lowest-direct",
         str(PLUGINS[plugin]), str(ROOT / "packages" / "roboscape_core"), torch_pin],
        check=True,
    )  # fmt: skip
    result = subprocess.run(
        [str(python), str(Path(__file__).with_name("plugin_alone.py")), plugin], capture_output=True, text=True
    )
    assert result.returncode == 0, result.stdout + result.stderr
    assert f"{plugin}: SFT loss" in result.stdout
