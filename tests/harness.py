"""The kill-and-resume harness: a command runs as a user runs it (`python -m lerobot_roboscape.cli.<name>`), is
SIGKILLed at a point inside its work, and is rerun (in the test's process: what the killed run left crosses the
process boundary); what it ends with is compared with an uninterrupted run."""

import importlib
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import torch
from safetensors.torch import load_file


def command(name: str, *args: str) -> list[str]:
    return [sys.executable, "-m", f"lerobot_roboscape.cli.{name}", *args]


def run(cmd: list[str], timeout: int = 600) -> subprocess.CompletedProcess:
    result = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    assert result.returncode == 0, result.stderr[-3000:]
    return result


def rerun(name: str, *args: str) -> None:
    """Rerun a command in this process (its `main`), as the resumption of a run killed in another process."""
    importlib.import_module(f"lerobot_roboscape.cli.{name}").main(list(args))


def kill_when(cmd: list[str], ready: Callable[[], bool], timeout: float = 600) -> None:
    """Start `cmd` and SIGKILL it as soon as `ready()` holds (polled every 10 ms). Fails if it ends first."""
    process = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + timeout
    try:
        while not ready():
            if process.poll() is not None:
                raise AssertionError(
                    f"{cmd[2]} ended (exit {process.returncode}) before the kill point: {process.stderr.read()[-2000:]}"
                )
            if time.time() > deadline:
                raise AssertionError(f"{cmd[2]} did not reach the kill point in {timeout} s")
            time.sleep(0.01)
    finally:
        process.send_signal(signal.SIGKILL)
        process.wait()
        process.stderr.close()


def assert_same_weights(expected: Path, got: Path) -> None:
    """Two safetensors files hold the same tensors, bit for bit."""
    a, b = load_file(expected), load_file(got)
    assert a.keys() == b.keys()
    different = [key for key in a if not torch.equal(a[key], b[key])]
    assert not different, f"tensors differ: {different[:5]}"
