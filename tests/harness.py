"""The kill-and-resume harness: a command runs as a user runs it (`python -m lerobot_roboscape.cli.<name>`), is
SIGKILLed at a point inside its work, and is rerun (in the test's process: what the killed run left crosses the
process boundary); what it ends with is compared with an uninterrupted run."""

import importlib
import json
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from datetime import date
from pathlib import Path

import imageio.v3 as iio
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


def kill_at_line(cmd: list[str], prefix: str, timeout: float = 600) -> None:
    """Start `cmd` and SIGKILL it as soon as it prints a line that begins with `prefix` (a stage header: the stage
    before it is complete, its own has begun). Fails if it ends first."""
    process = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    deadline, seen = time.time() + timeout, []
    try:
        for line in process.stdout:
            seen.append(line)
            if line.startswith(prefix):
                return
            if time.time() > deadline:
                raise AssertionError(f"{cmd[2]} did not print {prefix!r} in {timeout} s")
        raise AssertionError(f"{cmd[2]} ended before printing {prefix!r}: {''.join(seen)[-2000:]}")
    finally:
        process.send_signal(signal.SIGKILL)
        process.wait()
        process.stdout.close()


# What two uninterrupted runs of the same settings do not share either: the clock, and what is drawn against it.
TIMING_KEYS = {"seconds", "wall_seconds", "ppo_seconds", "stage_seconds", "date", "machine", "eval_s", "eval_ep_s"}
# A trainer's saved config records whether its run resumed (as LeRobot's train_config.json does); the cards show it.
RESUMED = "resume"
TIME_AXIS_FIGURES = {"ppo_curves.png", "curve.png"}  # plotted against PPO's clock


def _untimed(value):
    if isinstance(value, dict):
        return {
            k: _untimed(v)
            for k, v in value.items()
            if k not in TIMING_KEYS and k != RESUMED and not k.endswith("_per_s")
        }
    if isinstance(value, list):
        return [_untimed(v) for v in value]
    return value


def _untimed_markdown(text: str) -> list[str]:
    """The lines of a report but its time table and the line that names the machine and the date."""
    lines, in_times = [], False
    for line in text.splitlines():
        if line.startswith("## "):
            in_times = line.startswith("## Time")
        if not in_times and date.today().isoformat() not in line and f'"{RESUMED}": ' not in line:
            lines.append(line)
    return lines


def _logs(path: Path) -> bool:
    """TensorBoard's event files and the folders named for the time they were opened."""
    return path.name.startswith("events.out.tfevents") or any(
        part.replace(".", "").isdigit() and "." in part for part in path.parts
    )


def assert_same_outputs(expected: Path, got: Path) -> None:
    """Two runs' output folders hold the same files with the same contents, timing and the record of a resumed run
    aside: JSON (and JSON lines) without those fields; reports and cards without their time tables and those
    lines; safetensors tensor for tensor; videos by their number of frames and shape (the simulator's renders of an
    evaluation differ in a few pixels between two uninterrupted runs); every other file byte for byte."""
    files = lambda root: {p.relative_to(root) for p in root.rglob("*") if p.is_file() and not _logs(p)}  # noqa: E731
    names = files(expected)
    assert names == files(got), sorted(map(str, names ^ files(got)))
    different = []
    for name in sorted(names):
        a, b = expected / name, got / name
        if name.name in TIME_AXIS_FIGURES or a.read_bytes() == b.read_bytes():
            continue
        if name.suffix == ".json":
            same = _untimed(json.loads(a.read_text())) == _untimed(json.loads(b.read_text()))
        elif name.suffix == ".jsonl":
            rows = lambda p: [_untimed(json.loads(line)) for line in p.read_text().splitlines()]  # noqa: E731
            same = rows(a) == rows(b)
        elif name.suffix == ".md":
            same = _untimed_markdown(a.read_text()) == _untimed_markdown(b.read_text())
        elif name.suffix == ".safetensors":
            same = not _tensor_differences(a, b)
        elif name.suffix == ".mp4":
            same = iio.improps(a, plugin="pyav").shape == iio.improps(b, plugin="pyav").shape
        else:
            same = False
        if not same:
            different.append(str(name))
    assert not different, f"differ beyond timing: {different}"


def _tensor_differences(expected: Path, got: Path) -> list[str]:
    a, b = load_file(expected), load_file(got)
    if a.keys() != b.keys():
        return sorted(a.keys() ^ b.keys())
    return [key for key in a if not torch.equal(a[key], b[key])]


def assert_same_weights(expected: Path, got: Path) -> None:
    """Two safetensors files hold the same tensors, bit for bit."""
    different = _tensor_differences(expected, got)
    assert not different, f"tensors differ: {different[:5]}"
