"""What travels between this machine and the one where the world models are (pipeline/world_model_runs.py): the
plan of the runs the pack holds, and the record of each run that came back, as types read from and written to their
JSON (plan.json, results.json)."""

import dataclasses
import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

from lerobot_roboscape.io.records import OMIT_EMPTY, from_record, to_record
from roboscape_core.errors import InvalidInputError, MissingInputError

logger = logging.getLogger(__name__)
PLAN, RESULTS = "plan.json", "results.json"
PLAN_FORMAT = 2  # 2: every run's policy is rolled out for the replay, not the plain run's alone


def rollouts_file(tag: str) -> str:
    """The file of a run's rollouts for the replay, in the results' folder."""
    return f"replay_rollouts_{tag}.safetensors"


@dataclass(frozen=True)
class PlannedRun:
    """One PPO run of the pack: its method (as Table 1 names it), whether its env reads the ensemble's
    disagreement, its starts' file in the pack, and its env's and PPO's settings as JSON (those naming files of
    this machine left out: the device sets its own)."""

    method: str
    ensemble: bool
    starts: str
    env: dict
    ppo: dict


@dataclass(frozen=True)
class ReplayPlan:
    """From how many starts each run's policy is rolled out in the world model for the replay."""

    episodes: int


@dataclass
class Plan:
    """runs: by tag; curve_checkpoints: the checkpoints of each run kept for the checkpoint curve; replay: the
    replay's rollouts; ensemble: the ensemble members' settings (the lever's)."""

    runs: dict[str, PlannedRun]
    curve_checkpoints: int
    replay: ReplayPlan | None = field(default=None, metadata=OMIT_EMPTY)
    ensemble: dict = field(default_factory=dict, metadata=OMIT_EMPTY)

    def to_json(self) -> dict:
        return {"format": PLAN_FORMAT} | to_record(self)


def read_plan(folder: Path) -> Plan:
    path = Path(folder) / PLAN
    if not path.is_file():
        raise MissingInputError(f"{path} is missing: `roboscape-experiment --world_model_runs=...` writes the pack")
    data = json.loads(path.read_text())
    if data.get("format") != PLAN_FORMAT:
        raise InvalidInputError(f"{path} has format {data.get('format')}; this version reads {PLAN_FORMAT}")
    return from_record(Plan, data)


@dataclass(frozen=True)
class RunRecord:
    """A run as it came back: its method, its folder and final checkpoint (relative to the results' folder as
    written, absolute once read back here), its seconds, or the error it failed with."""

    method: str
    folder: Path
    final: Path | None = field(default=None, metadata=OMIT_EMPTY)
    seconds: float | None = field(default=None, metadata=OMIT_EMPTY)
    error: str | None = field(default=None, metadata=OMIT_EMPTY)

    def under(self, root: Path) -> "RunRecord":
        return dataclasses.replace(self, folder=root / self.folder, final=self.final and root / self.final)


@dataclass
class PackResults:
    """What `run_pack` reports: the done threshold chosen there, its GPU, PPO's budget, every run, and the file of
    each completed run's rollouts for the replay, by tag."""

    done: dict
    gpu: str | None
    time_budget_s: float | None
    runs: dict[str, RunRecord]
    replays: dict[str, str] = field(default_factory=dict, metadata=OMIT_EMPTY)

    def to_json(self) -> dict:
        return to_record(self)


def read_results(folder: Path, needed: str) -> PackResults:
    """What `run_pack` wrote into `folder` (brought back here): the runs that completed, their folders absolute (a
    failed one is left out, with a warning naming its error), and their rollouts; the run of the method `needed`
    (the plain run) must be there with its rollouts."""
    folder, path = Path(folder), Path(folder) / RESULTS
    if not path.is_file():
        raise MissingInputError(f"{path} is missing: the world-model runs have not been brought back into {folder}")
    results = from_record(PackResults, json.loads(path.read_text()))
    results.runs = {tag: run.under(folder) for tag, run in results.runs.items()}
    for tag, run in list(results.runs.items()):
        if run.error is not None:
            logger.warning("%s: the run %r failed where it ran (%s); it is left out", path, run.method, run.error)
            del results.runs[tag]
        elif not run.final.is_dir():
            raise MissingInputError(f"{path}: the final checkpoint {run.final} of {run.method!r} is missing")
    missing = [
        tag for tag in results.runs if tag not in results.replays or not (folder / results.replays[tag]).is_file()
    ]
    if needed not in [run.method for run in results.runs.values()] or missing:
        raise MissingInputError(
            f"{path}: the run {needed!r} in the world model or the rollouts of the replay of {missing} did not come "
            f"back into {folder}"
        )
    return results
