"""Models trained elsewhere (--world_models: on a lent GPU, or by an earlier run on another machine), taken into a
run where its own would train: each of the action and text world models and the tokenizer they learned that the
folder brings (those it does not are trained by the run); and a run's models carried out in that shape, for a run on
another machine."""

import json
import logging
import shutil
from collections.abc import Callable
from pathlib import Path

from lerobot_roboscape.pipeline.config import PipelineConfig
from lerobot_roboscape.pipeline.layout import TOKENIZER_DIR, WorldModelPaths, world_model_dir
from lerobot_roboscape.pipeline.resume import run_once
from lerobot_roboscape.tokenizer.modeling_tokenizer import VisualTokenizer
from lerobot_roboscape.tokenizer.token_cache import tokenizer_fingerprint
from lerobot_roboscape.training.checkpoints import CHECKPOINTS, FINAL, RESUME_ONLY
from lerobot_roboscape.training.loop import TRAIN_CONFIG
from lerobot_roboscape.world_model.modeling_world_model import STWorldModel
from lerobot_roboscape.world_model.train import TOKENIZER_FINGERPRINT
from roboscape_core.errors import InvalidInputError, MissingInputError

logger = logging.getLogger(__name__)
GIVEN_TOKENIZER = "tokenizer"  # the folder of --world_models holding the tokenizer they learned, if they bring it
# What travels of a training output_dir: the model and its records (config, log, curves, done tuning), not the
# checkpoints a killed run resumes from nor TensorBoard's events.
NOT_CARRIED = shutil.ignore_patterns(*RESUME_ONLY)


def brought(cfg: PipelineConfig) -> set[str]:
    """What --world_models brings, of the tokenizer/, action/ and text/ folders (none without the flag); a folder
    that brings none of them is refused, so that a mistyped path trains nothing in its place unnoticed."""
    if cfg.world_models is None:
        return set()
    given = {name for name in (GIVEN_TOKENIZER, *WorldModelPaths._fields) if (Path(cfg.world_models) / name).is_dir()}
    if not given:
        raise MissingInputError(
            f"--world_models={cfg.world_models} holds none of {GIVEN_TOKENIZER}/, action/ and text/: each a training "
            "output_dir (scripts/experiments/carry_world_models.py and device_world_models.sh unpack write them)"
        )
    return given


def given_world_model(cfg: PipelineConfig, out: Path, tokenizer_path: Path, control: str) -> Path:
    """The `control` world model of --world_models (a roboscape-train-wm output_dir), taken once it is found to
    read the run's tokenizer's grids."""
    source = Path(cfg.world_models) / control

    def check():
        model = STWorldModel.from_pretrained(str(source / FINAL)).config
        tokenizer = VisualTokenizer.from_pretrained(str(tokenizer_path))
        theirs = {"control": model.control, "vocab_size": model.vocab_size, "tokens_per_side": model.tokens_per_side}
        ours = {"control": control, "vocab_size": tokenizer.config.codebook_size}
        ours["tokens_per_side"] = tokenizer.config.tokens_per_side
        trained = source / TRAIN_CONFIG  # its training run's record names the tokens it learned
        if trained.is_file() and TOKENIZER_FINGERPRINT in (record := json.loads(trained.read_text())):
            theirs["tokenizer"], ours["tokenizer"] = record[TOKENIZER_FINGERPRINT], tokenizer_fingerprint(tokenizer)
        else:
            logger.warning("%s names no tokenizer: only its token grid is checked against the run's", trained)
        if theirs != ours:
            raise InvalidInputError(
                f"--world_models: {source / FINAL} is not the {control} model of this run's tokenizer "
                f"({tokenizer_path}): it has {theirs}, the run needs {ours}"
            )

    return _taken(cfg, source, out / world_model_dir(control), "world_model", check)


def given_tokenizer(cfg: PipelineConfig, folder: Path) -> Path:
    """The tokenizer beside --world_models (a roboscape-train-tokenizer output_dir), taken once it is found to read
    the run's cameras."""
    source = Path(cfg.world_models) / GIVEN_TOKENIZER

    def check():
        size = VisualTokenizer.from_pretrained(str(source / FINAL)).config.image_size
        if size != cfg.data.image_size:
            raise InvalidInputError(
                f"--world_models: {source / FINAL} reads {size} px images, the run's cameras make "
                f"--data.image_size={cfg.data.image_size}"
            )

    return _taken(cfg, source, folder, "tokenizer", check)


def _taken(cfg: PipelineConfig, source: Path, folder: Path, what: str, check: Callable[[], None]) -> Path:
    """A model trained elsewhere (`source`, a training output_dir) copied with its logs and curves into `folder`,
    where the run's own would train, once `check()` passes; returns its final model. Its weights' size and time
    name it: other weights copied there rerun the stages that read them."""
    weights = source / FINAL / "model.safetensors"
    if not weights.is_file():
        raise MissingInputError(
            f"--world_models={cfg.world_models}: no {weights}; it holds action/ and text/, each a roboscape-train-wm "
            f"output_dir, and optionally {GIVEN_TOKENIZER}/, the roboscape-train-tokenizer output_dir they learned "
            "(scripts/experiments/device_world_models.sh unpack writes them)"
        )
    stat = weights.stat()
    settings = {what: str(source.resolve()), "bytes": stat.st_size, "modified_ns": stat.st_mtime_ns}

    def take():
        check()
        shutil.copytree(source, folder, ignore=shutil.ignore_patterns(CHECKPOINTS))  # the model, its logs, curves

    run_once(folder, settings, cfg.fresh, take)
    return folder / FINAL


def carry(out: Path, dest: Path) -> dict[str, int]:
    """The tokenizer and the world models the run in `out` has trained, written to `dest` as --world_models takes
    them (tokenizer/, action/, text/), so that a run on another machine goes on from them: a run stopped after its
    tokenizer carries that alone, and the next trains its world models on it; {folder: bytes}. Written beside `dest`
    and moved into place when complete."""
    sources = {GIVEN_TOKENIZER: out / TOKENIZER_DIR} | {c: out / world_model_dir(c) for c in WorldModelPaths._fields}
    trained = {name: source for name, source in sources.items() if (source / FINAL / "model.safetensors").is_file()}
    if GIVEN_TOKENIZER not in trained:
        raise MissingInputError(
            f"{sources[GIVEN_TOKENIZER] / FINAL / 'model.safetensors'} does not exist: train the run's tokenizer first "
            f"(roboscape-demo --output_dir={out} --stop_after=tokenizer)"
        )
    partial = dest.with_name(dest.name + ".partial")
    shutil.rmtree(partial, ignore_errors=True)
    for name, source in trained.items():
        shutil.copytree(source, partial / name, ignore=NOT_CARRIED)
    shutil.rmtree(dest, ignore_errors=True)
    partial.rename(dest)
    return {name: sum(f.stat().st_size for f in (dest / name).rglob("*") if f.is_file()) for name in trained}
