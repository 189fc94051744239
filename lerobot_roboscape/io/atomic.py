"""Outputs that appear complete or not at all: written beside their target under a hidden name, then renamed
(a rename within one file system is atomic), so a kill or a full disk never leaves a partial file that a later run
would accept."""

import os
import tempfile
from pathlib import Path


def make_tmp_dir(parent: Path, name: str) -> Path:
    """A fresh hidden directory in `parent` to build `parent/name` in, then `os.replace` it into place."""
    parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{name}.", dir=parent))
    tmp.chmod(0o755)  # mkdtemp makes it private; the final directory should not be
    return tmp


def write_text_atomically(path: Path, text: str) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        tmp.write_text(text)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
