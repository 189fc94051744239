"""What travels between this machine and the one where the world models are (pipeline/world_model_runs.py): the
plan of the runs the pack holds, and the record of each run that came back, as types read from and written to their
JSON (plan.json, results.json)."""

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

from roboscape_core.errors import InvalidInputError, MissingInputError

logger = logging.getLogger(__name__)
PLAN, RESULTS = "plan.json", "results.json"
PLAN_FORMAT = 1
ROLLOUTS = "replay_rollouts.safetensors"


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
    """The run whose policy is rolled out in the world model for the replay, and from how many starts."""

    tag: str
    episodes: int


@dataclass
class Plan:
    """runs: by tag; curve_checkpoints: the checkpoints of each run kept for the checkpoint curve; replay: the
    replay's run; ensemble: the ensemble members' settings (the lever's)."""

    runs: dict[str, PlannedRun]
    curve_checkpoints: int
    replay: ReplayPlan | None = None
    ensemble: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        data = {"format": PLAN_FORMAT, "runs": {tag: vars(run) for tag, run in self.runs.items()}}
        if self.replay is not None:
            data["replay"] = vars(self.replay)
        if self.ensemble:
            data["ensemble"] = self.ensemble
        return data | {"curve_checkpoints": self.curve_checkpoints}


def read_plan(folder: Path) -> Plan:
    path = Path(folder) / PLAN
    if not path.is_file():
        raise MissingInputError(f"{path} is missing: `roboscape-experiment --world_model_runs=...` writes the pack")
    data = json.loads(path.read_text())
    if data.get("format") != PLAN_FORMAT:
        raise InvalidInputError(f"{path} has format {data.get('format')}; this version reads {PLAN_FORMAT}")
    return Plan(
        {tag: PlannedRun(**run) for tag, run in data["runs"].items()},
        data["curve_checkpoints"],
        ReplayPlan(**data["replay"]) if data.get("replay") else None,
        data.get("ensemble", {}),
    )


@dataclass(frozen=True)
class RunRecord:
    """A run as it came back: its method, its folder and final checkpoint (relative to the results' folder as
    written, absolute once read back here), its seconds, or the error it failed with."""

    method: str
    folder: Path
    final: Path | None = None
    seconds: float | None = None
    error: str | None = None

    def to_json(self) -> dict:
        data = {"method": self.method, "folder": str(self.folder)}
        if self.error is not None:
            return data | {"error": self.error}
        return data | {"seconds": self.seconds, "final": str(self.final)}

    @classmethod
    def from_json(cls, data: dict, root: Path) -> "RunRecord":
        final = data.get("final")
        return cls(
            data["method"], root / data["folder"], final and root / final, data.get("seconds"), data.get("error")
        )


@dataclass
class PackResults:
    """What `run_pack` reports: the done threshold chosen there, its GPU, PPO's budget, every run, and the replay's
    rollouts' file (None where the replay's run failed)."""

    done: dict
    gpu: str | None
    time_budget_s: float | None
    runs: dict[str, RunRecord]
    replay_rollouts: str | None = None
    replay_tag: str | None = None

    def to_json(self) -> dict:
        data = {"done": self.done, "gpu": self.gpu, "time_budget_s": self.time_budget_s}
        data["runs"] = {tag: run.to_json() for tag, run in self.runs.items()}
        if self.replay_rollouts is not None:
            data["replay"] = {"tag": self.replay_tag, "file": self.replay_rollouts}
        return data


def read_results(folder: Path) -> PackResults:
    """What `run_pack` wrote into `folder` (brought back here): the runs that completed, their folders absolute (a
    failed one is left out, with a warning naming its error); the plain run and its rollouts must be there."""
    path = Path(folder) / RESULTS
    if not path.is_file():
        raise MissingInputError(f"{path} is missing: the world-model runs have not been brought back into {folder}")
    data = json.loads(path.read_text())
    runs = {tag: RunRecord.from_json(run, Path(folder)) for tag, run in data["runs"].items()}
    for tag, run in list(runs.items()):
        if run.error is not None:
            logger.warning("%s: the run %r failed where it ran (%s); it is left out", path, run.method, run.error)
            del runs[tag]
        elif not run.final.is_dir():
            raise MissingInputError(f"{path}: the final checkpoint {run.final} of {run.method!r} is missing")
    replay = data.get("replay") or {}
    if not replay or not (Path(folder) / replay["file"]).is_file():
        raise MissingInputError(
            f"{path}: the plain run in the world model or the rollouts of its replay ({ROLLOUTS}) did not come back "
            f"into {folder}"
        )
    return PackResults(data["done"], data["gpu"], data["time_budget_s"], runs, replay["file"], replay["tag"])
