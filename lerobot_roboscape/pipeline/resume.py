"""Resuming a run: a stage writes into its own folder and, once complete, a stage.json with the settings it ran
with; a rerun with the same settings skips it, so a killed run resumes where it stopped. A training stage keeps
its checkpoints across a kill (`prepare`) and resumes from the last one.

A stage's settings name the models it reads by path, and a path stays the same when the model behind it is
trained again with other settings. So the settings of every model a stage reads (a pretrained_model folder of
another stage) count among its own: retraining the world models reruns the reports and runs made with them."""

import hashlib
import json
import shutil
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

from lerobot_roboscape.io.atomic import write_text_atomically
from lerobot_roboscape.io.records import from_record, to_record
from lerobot_roboscape.training.checkpoints import FINAL

STAGE_FILE = "stage.json"


@dataclass(frozen=True)
class StageRecord:
    """A completed stage's stage.json: the settings it ran with and the seconds its (last) run took."""

    settings: object  # the stage's config as JSON
    seconds: float | None = None

    @classmethod
    def read(cls, folder: Path) -> "StageRecord | None":
        marker = Path(folder) / STAGE_FILE
        return from_record(cls, json.loads(marker.read_text())) if marker.is_file() else None


def _jsonable(settings) -> dict:
    plain = json.loads(
        json.dumps(settings, default=lambda v: asdict(v) if hasattr(v, "__dataclass_fields__") else str(v))
    )
    inputs = {path: digest for path in sorted(_strings(plain)) if (digest := _model_digest(path))}
    return plain | {"input_models": inputs} if inputs else plain


def _strings(value) -> set[str]:
    if isinstance(value, str):
        return {value}
    if isinstance(value, dict):
        value = list(value.values())
    return set().union(*map(_strings, value)) if isinstance(value, list) else set()


def _model_digest(path: str) -> str | None:
    """A digest of the settings of the stage that made the model at `path` (a pretrained_model folder beside a
    stage.json); None for any other string."""
    record = StageRecord.read(Path(path).parent) if Path(path).name == FINAL else None
    if record is None:
        return None
    made_with = json.dumps(record.settings, sort_keys=True)
    return hashlib.sha256(made_with.encode()).hexdigest()[:16]


_began: dict[Path, float] = {}  # when each stage folder's current run started


def is_done(folder: Path, settings, fresh: bool) -> bool:
    """The stage in `folder` completed with these settings (then its outputs are kept and the stage skipped). A
    setting added to the stage's config after it ran counts as unchanged while empty (None, [], 0 or false): new
    options leave the old behaviour at those defaults, and a finished evaluation or training stays finished."""
    record = None if fresh else StageRecord.read(folder)
    if record is None:
        return False
    recorded, now = record.settings, _jsonable(settings)
    if isinstance(recorded, dict) and isinstance(now, dict):
        now = {k: v for k, v in now.items() if k in recorded or v not in (None, [], 0)}  # 0 == False
    return recorded == now


def start(folder: Path) -> Path:
    """Clear what an unfinished or differently-configured run of the stage left in `folder`."""
    shutil.rmtree(folder, ignore_errors=True)
    _began[Path(folder)] = time.time()
    return Path(folder)


def prepare(folder: Path, settings, fresh: bool, budgets: tuple[str, ...] = ()) -> bool:
    """Make `folder` ready for a training stage; True when it holds a run to resume from (its checkpoints): an
    interrupted one with the same settings, or one that differs only in a larger budget (a setting named in
    `budgets`: the run goes on where it stopped); False when it was cleared for a new run."""
    folder, started = Path(folder), Path(folder) / "stage.started.json"
    now = _jsonable(settings)
    if not fresh and started.is_file() and _same_or_longer(json.loads(started.read_text()), now, budgets):
        write_text_atomically(started, json.dumps(now, indent=2))
        _began[folder] = time.time()
        return True
    start(folder).mkdir(parents=True)
    write_text_atomically(started, json.dumps(now, indent=2))
    return False


def _same_or_longer(before, now, budgets: tuple[str, ...]) -> bool:
    """`now` asks for the run `before` started, or for the same run with larger budgets (None: no limit)."""
    if before == now:
        return True
    if not budgets or not (isinstance(before, dict) and isinstance(now, dict)):
        return False
    rest = lambda settings: {k: v for k, v in settings.items() if k not in budgets}  # noqa: E731
    longer = lambda old, new: old == new or new is None or (old is not None and new > old)  # noqa: E731
    return rest(before) == rest(now) and all(longer(before.get(k), now.get(k)) for k in budgets)


def mark_done(folder: Path, settings, seconds: float | None = None) -> None:
    """Record the stage's settings and the seconds its (last) run took (`seconds`: those it took elsewhere)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    began = _began.pop(folder, time.time())
    seconds = time.time() - began if seconds is None else seconds
    write_text_atomically(
        folder / STAGE_FILE, json.dumps(to_record(StageRecord(_jsonable(settings), seconds)), indent=2)
    )


def stage_seconds(folder: Path) -> float | None:
    record = StageRecord.read(folder)
    return record and record.seconds


def run_once(folder: Path, settings, fresh: bool, work: Callable[[], object]) -> bool:
    """Run `work` into a cleared `folder` and record it complete, unless it already completed with these
    settings; True when it ran. The record holds the settings as they were asked for, before `work` (which may
    fill fields of the config in place)."""
    if is_done(folder, settings, fresh):
        return False
    asked = _jsonable(settings)
    start(folder)
    work()
    mark_done(folder, asked)
    return True


def train_once(
    folder: Path, settings, fresh: bool, train: Callable[[bool], object], budgets: tuple[str, ...] = ()
) -> bool:
    """Run a training stage, `train(resume)`, unless it already completed with these settings: resume is True when
    `folder` holds an interrupted run with the same settings, or a run that differs only in a larger budget (its
    checkpoints kept: see `prepare`), False when it was cleared for a new run. True when it ran."""
    if is_done(folder, settings, fresh):
        return False
    asked = _jsonable(settings)  # as asked for: a trainer may fill fields of its config (the action statistics)
    train(prepare(folder, settings, fresh, budgets))
    mark_done(folder, asked)
    return True
