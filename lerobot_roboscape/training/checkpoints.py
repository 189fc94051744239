"""The checkpoint layout of every trainer (tokenizer, world models, reward models, PPO):

    output_dir/checkpoints/NNNNNNNN/...     one folder per saved step or iteration
    output_dir/checkpoints/last             a file naming the newest, which `resume` continues from
    .../pretrained_model                    the model as `from_pretrained` loads it

A checkpoint is built in a hidden folder beside its final place and renamed into place once complete, and `last`
is replaced only then: a kill at any moment leaves the previous checkpoint as the one to resume from.
"""

import os
import shutil
from pathlib import Path

import numpy as np
from lerobot.utils.constants import CHECKPOINTS_DIR, LAST_CHECKPOINT_LINK, PRETRAINED_MODEL_DIR

from lerobot_roboscape.io.atomic import make_tmp_dir, write_text_atomically
from roboscape_core.errors import MissingInputError

# LeRobot's names, so that its tools and ours find the same folders.
CHECKPOINTS, LAST, FINAL = CHECKPOINTS_DIR, LAST_CHECKPOINT_LINK, PRETRAINED_MODEL_DIR
LOGS = "logs"  # TensorBoard's events, under output_dir
# What of a training output_dir only a resumed run or TensorBoard reads: it stays when the model travels.
RESUME_ONLY = (CHECKPOINTS, LOGS)
PPO_CONFIG_JSON = "ppo_config.json"  # beside a roboscape-ppo checkpoint's FINAL: the flags it trained under


def checkpoint_name(step: int) -> str:
    return f"{step:08d}"


def last_checkpoint(output_dir: Path) -> Path | None:
    pointer = Path(output_dir) / CHECKPOINTS / LAST
    if not pointer.is_file():
        return None
    path = Path(output_dir) / CHECKPOINTS / pointer.read_text().strip()
    return path if path.is_dir() else None


def begin_checkpoint(output_dir: Path, step: int) -> Path:
    """The hidden folder to write checkpoint `step` into; `publish_checkpoint` moves it into place."""
    return make_tmp_dir(Path(output_dir) / CHECKPOINTS, checkpoint_name(step))


def publish_checkpoint(output_dir: Path, step: int, tmp: Path, keep: int | None = None) -> Path:
    """Move the complete checkpoint `tmp` into place, point `last` at it, and keep only the newest `keep`."""
    root = Path(output_dir) / CHECKPOINTS
    name = checkpoint_name(step)
    shutil.rmtree(root / name, ignore_errors=True)
    os.replace(tmp, root / name)
    write_text_atomically(root / LAST, name)
    if keep is not None:
        for old in sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith("."))[:-keep]:
            shutil.rmtree(old)
    return root / name


def publish_final(output_dir: Path) -> Path:
    """output_dir/FINAL, where every trainer's model lives and what travels of its output_dir: lerobot-train and PPO
    keep theirs only in their checkpoints, so it is copied out of the newest, built beside its place, whenever that
    is newer (a run resumed with a larger budget); a carried run, without checkpoints, keeps the one it brought.
    The files beside the checkpoint's FINAL (PPO's flags, its reward) come beside output_dir/FINAL with it, so that
    what reads them beside a model (the Hub card, the done refresh's world model) reads either alike."""
    final = Path(output_dir) / FINAL
    newest = (last_checkpoint(output_dir) or Path(output_dir) / CHECKPOINTS / LAST) / FINAL  # lerobot's is a link
    if not newest.is_dir():
        if final.is_dir():
            return final
        raise MissingInputError(
            f"{output_dir} holds neither {FINAL}/ nor {CHECKPOINTS}/{LAST}/{FINAL}/: a training run carried without "
            "its model; train it again (--fresh) where its data is"
        )
    # copytree keeps the checkpoint's mtime on the copy: an equal one is that checkpoint, a later checkpoint newer.
    if final.is_dir() and final.stat().st_mtime >= newest.stat().st_mtime:
        return final
    for described in newest.parent.iterdir():
        if described.is_file():
            write_text_atomically(Path(output_dir) / described.name, described.read_text())
    tmp = make_tmp_dir(Path(output_dir), FINAL)
    shutil.copytree(newest, tmp, dirs_exist_ok=True)
    if final.is_dir():
        shutil.rmtree(final)
    os.replace(tmp, final)
    return final


def spread_checkpoints(output_dir: Path, n: int) -> list[Path]:
    """`n` of a run's saved checkpoints (or all, if fewer) evenly spread over them, the first and the last among
    them, in order."""
    saved = sorted(f for f in (Path(output_dir) / CHECKPOINTS).iterdir() if f.name.isdigit())
    return [saved[int(i)] for i in np.unique(np.linspace(0, len(saved) - 1, n).round())] if saved else []
