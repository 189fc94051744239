"""A run's completed stages carried to another machine (no Hub here, and a machine's outputs die with it): every
stage folder that completed (it holds its stage.json), the text model's goals and the trajectory file, without what
only a killed run resumes from (checkpoints, logs), the token caches a stage rebuilds nor the datasets' object masks,
written to a folder that travels; then taken into a run's output_dir on the next machine, where those stages count
as done and are skipped. A stage records its inputs by absolute path, so the run must sit where it sat: a folder
carried from elsewhere is refused by name."""

import json
import shutil
from pathlib import Path

from lerobot_roboscape.dataset.segmentation import SEGMENTATION_DIR, SEGMENTATION_META
from lerobot_roboscape.io.atomic import make_tmp_dir, write_text_atomically
from lerobot_roboscape.pipeline.layout import GOAL_FILE, TOKEN_CACHE_DIR, TRAJECTORIES_DIR
from lerobot_roboscape.pipeline.resume import STAGE_FILE
from lerobot_roboscape.training.checkpoints import RESUME_ONLY
from roboscape_core.errors import InvalidInputError, MissingInputError

MANIFEST = "carried.json"  # {"run": the run's absolute path, "stages": {folder: bytes}}
# The masks are 90% of a collection's bytes and only the tokenizer and the reports read them, all before the
# claim: a carried dataset has none (its record of them goes too, so a stage that needs them says so).
NOT_CARRIED = (*RESUME_ONLY, TOKEN_CACHE_DIR, SEGMENTATION_DIR, Path(SEGMENTATION_META).name)
# Outputs a stage keeps outside its own folder: the goals, the trajectory file the converted dataset was made from.
EXTRAS = (GOAL_FILE, TRAJECTORIES_DIR)


def completed_stages(out: Path) -> list[str]:
    """The run's completed stage folders, relative to it; a stage inside another stage's folder goes with it."""
    folders = sorted(marker.parent.relative_to(out) for marker in Path(out).rglob(STAGE_FILE))
    # Hidden folders are unfinished work (episodes a collection resumes from, a stage being built).
    folders = [f for f in folders if not any(part in NOT_CARRIED or part.startswith(".") for part in f.parts)]
    return [str(f) for f in folders if not any(parent in folders for parent in f.parents)]


def _size(path: Path) -> int:
    return path.stat().st_size if path.is_file() else sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


def carry_stages(out: Path, dest: Path) -> dict[str, int]:
    """Every completed stage of the run in `out` (and its goal file, once made) written to `dest`, built beside it
    and moved into place when complete; {folder: bytes}."""
    out = Path(out).resolve()
    stages = completed_stages(out)
    if not stages:
        raise MissingInputError(f"{out} holds no completed stage (no {STAGE_FILE} under it): nothing to carry")
    dest = Path(dest)
    tmp = make_tmp_dir(dest.parent, dest.name)
    for stage in stages:
        shutil.copytree(out / stage, tmp / stage, ignore=shutil.ignore_patterns(*NOT_CARRIED))
    for extra in (e for e in EXTRAS if (out / e).exists()):
        (tmp / extra).parent.mkdir(parents=True, exist_ok=True)
        copy = shutil.copy2 if (out / extra).is_file() else shutil.copytree
        copy(out / extra, tmp / extra)
        stages.append(extra)
    sizes = {stage: _size(tmp / stage) for stage in stages}
    write_text_atomically(tmp / MANIFEST, json.dumps({"run": str(out), "stages": sizes}, indent=1))
    shutil.rmtree(dest, ignore_errors=True)
    tmp.rename(dest)
    return sizes


def take_stages(carried: Path, out: Path) -> list[str]:
    """The stages carried in `carried` copied into the run in `out`, each moved into place when complete; a stage
    `out` already completed is kept as it is. Returns those taken."""
    manifest = Path(carried) / MANIFEST
    if not manifest.is_file():
        raise MissingInputError(f"{manifest} does not exist: carry a run's stages with carry_stages first")
    record, out = json.loads(manifest.read_text()), Path(out).resolve()
    if record["run"] != str(out):
        raise InvalidInputError(
            f"{manifest}: its stages ran in {record['run']} and name their inputs by that path; take them into a "
            f"run there, not into {out}"
        )
    taken = []
    for stage in record["stages"]:
        source, target = Path(carried) / stage, out / stage
        if (target / STAGE_FILE).is_file() or (stage in EXTRAS and target.exists()):
            continue
        tmp = make_tmp_dir(target.parent, target.name)
        if source.is_file():
            shutil.copy2(source, tmp / target.name)
            (tmp / target.name).rename(target)
            tmp.rmdir()
        else:
            shutil.copytree(source, tmp, dirs_exist_ok=True)
            shutil.rmtree(target, ignore_errors=True)  # what an unfinished run of the stage left
            tmp.rename(target)
        taken.append(stage)
    return taken
