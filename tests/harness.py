"""The kill-and-resume harness: a command runs as a user runs it (`python -m lerobot_roboscape.cli.<name>`), is
SIGKILLed at a point inside its work (`kill_when`, `kill_at_line`), and is rerun, in the test's process (`rerun`)
or in another (`run`): what the killed run left crosses the process boundary. What it ends with is compared with
an uninterrupted run (`output_differences`, `assert_same_weights`).

The killed runs are forked from a server that has imported the command (a forkserver), not started in a fresh
interpreter: importing a command takes about 14 s on 2 cores, longer than most smoke-scale stages, and a chain of
kills at every stage boundary starts one run per stage."""

import contextlib
import importlib
import json
import multiprocessing
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
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


# The server that the killed runs are forked from: it imports the first command it forks and nothing more, so a
# fork copies no thread at work and no simulator renderer (SAPIEN's does not survive a fork; each run makes its own).
_FORKS = multiprocessing.get_context("forkserver")


def _forked_main(module: str, args: list[str], output: str, env: dict[str, str]) -> None:
    os.setsid()  # its own process group, so that a kill reaches what it starts too (lerobot-train, simulator workers)
    os.environ.clear()
    os.environ.update(env)  # the test's environment now, not the server's when it started
    fd = os.open(output, os.O_WRONLY | os.O_APPEND)
    os.dup2(fd, 1)
    os.dup2(fd, 2)
    importlib.import_module(module).main(args)


class _Forked:
    """`python -m <module> *args` (a lerobot_roboscape.cli command) forked from the server, its stdout and stderr
    to a temporary file."""

    def __init__(self, cmd: list[str]):
        module, args = cmd[2], cmd[3:]
        _FORKS.set_forkserver_preload([module])  # read once, as the server starts
        fd, output = tempfile.mkstemp(prefix=f"{module}.", suffix=".log")
        os.close(fd)
        self.output, self._read, self._pending = Path(output), 0, ""
        self._process = _FORKS.Process(target=_forked_main, args=(module, args, output, dict(os.environ)))
        self._process.start()

    def poll(self) -> int | None:
        return self._process.exitcode

    def lines(self) -> list[str]:
        """The whole lines it has written since the last call."""
        with self.output.open("rb") as file:
            file.seek(self._read)
            written = file.read()
        self._read += len(written)
        *complete, self._pending = (self._pending + written.decode(errors="replace")).split("\n")
        return complete

    def tail(self) -> str:
        return self.output.read_text(errors="replace")[-2000:]

    def kill(self) -> None:
        """SIGKILL its process group (a no-op once it has ended), and remove its output."""
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self._process.pid, signal.SIGKILL)
        self._process.join()
        self.output.unlink()


def kill_when(cmd: list[str], ready: Callable[[], bool], timeout: float = 600) -> None:
    """Fork `cmd` and SIGKILL it as soon as `ready()` holds (polled every 10 ms). Fails if it ends first."""
    process, deadline = _Forked(cmd), time.time() + timeout
    try:
        while not ready():
            if process.poll() is not None:
                raise AssertionError(f"{cmd[2]} ended (exit {process.poll()}) before the kill point: {process.tail()}")
            if time.time() > deadline:
                raise AssertionError(f"{cmd[2]} did not reach the kill point in {timeout} s")
            time.sleep(0.01)
    finally:
        process.kill()


def kill_at_line(cmd: list[str], prefix: str, timeout: float = 600) -> None:
    """Fork `cmd` and SIGKILL it as soon as it prints a line that begins with `prefix` (a stage header: the stage
    before it is complete, its own has begun). Fails if it ends first or stays silent past the timeout."""
    process, deadline = _Forked(cmd), time.time() + timeout
    try:
        while True:
            ended = process.poll() is not None  # before reading: what it wrote before it ended is read
            if any(line.startswith(prefix) for line in process.lines()):
                return
            if ended:
                raise AssertionError(f"{cmd[2]} ended before printing {prefix!r}: {process.tail()}")
            if time.time() > deadline:
                raise AssertionError(f"{cmd[2]} did not print {prefix!r} in {timeout} s")
            time.sleep(0.01)
    finally:
        process.kill()


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


DATE = re.compile(r"\d{4}-\d{2}-\d{2}")
MINUTES = re.compile(r"\d+(\.\d+)? min\b")


def _untimed_markdown(text: str) -> list[str]:
    """The lines of a report but its time table, the line that names the machine and the date, and the resumed
    flag; durations in minutes elsewhere are blanked."""
    lines, in_times = [], False
    for line in text.splitlines():
        if line.startswith("## "):
            in_times = line.startswith("## Time")
        if not in_times and not DATE.search(line) and f'"{RESUMED}": ' not in line:
            lines.append(MINUTES.sub("? min", line))
    return lines


def _logs(path: Path) -> bool:
    """TensorBoard's event files and the folders named for the time they were opened (`path` inside a run)."""
    return path.name.startswith("events.out.tfevents") or any(
        part.replace(".", "").isdigit() and "." in part for part in path.parts
    )


def output_differences(expected: Path, got: Path) -> list[str]:
    """What differs between two runs' output folders, timing and the record of a resumed run aside: JSON (and JSON
    lines) compared without those fields; reports and cards without their time tables, dates, durations and the
    resumed flag; safetensors tensor for tensor; videos by their number of frames and shape (the simulator's
    renders of an evaluation differ in a few pixels between two uninterrupted runs); every other file byte for
    byte. Figures drawn against PPO's clock are not compared."""
    assert expected.is_dir() and got.is_dir(), (expected, got)

    def files(root: Path) -> set[Path]:
        return {p.relative_to(root) for p in root.rglob("*") if p.is_file() and not _logs(p.relative_to(root))}

    names, others = files(expected), files(got)
    assert names, f"{expected} holds no output to compare"
    if names != others:
        return [f"only in one run: {sorted(map(str, names ^ others))}"]
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
    return different


def _tensor_differences(expected: Path, got: Path) -> list[str]:
    a, b = load_file(expected), load_file(got)
    if a.keys() != b.keys():
        return sorted(a.keys() ^ b.keys())
    return [key for key in a if not torch.equal(a[key], b[key])]


def assert_same_weights(expected: Path, got: Path) -> None:
    """Two safetensors files hold the same tensors, bit for bit."""
    different = _tensor_differences(expected, got)
    assert not different, f"tensors differ: {different[:5]}"
