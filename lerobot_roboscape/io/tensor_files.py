"""Files of tensors with a record beside them (safetensors with string metadata): the env's starts and goals, the
controllability sets, the done report's token episodes, rollouts. Written under a temporary name and moved into
place once complete; read with the file and its writer named in any error."""

from pathlib import Path

import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import save_file

from roboscape_core.errors import InvalidInputError


def save_tensors(path: str | Path, tensors: dict[str, torch.Tensor], metadata: dict[str, str]) -> Path:
    """`tensors` (moved to the CPU, made contiguous) and `metadata` in `path`, which appears only once complete."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    save_file({k: v.detach().cpu().contiguous() for k, v in tensors.items()}, str(tmp), metadata=metadata)
    tmp.replace(path)
    return path


def load_tensors(
    path: str | Path, writer: str, keys: tuple[str, ...] = (), device: str = "cpu"
) -> tuple[dict[str, str], dict[str, torch.Tensor]]:
    """(metadata, tensors) of a file `writer` (the function that writes such files) wrote; a file that is not one,
    or lacks the metadata `keys`, is refused with both named."""
    try:
        with safe_open(str(path), "pt", device=str(device)) as f:
            metadata = f.metadata() or {}
            tensors = {name: f.get_tensor(name) for name in f.keys()}  # noqa: SIM118 (safe_open is not a dict)
    except (OSError, ValueError, SafetensorError) as error:
        raise _not_one(path, writer, error) from error
    if missing := [key for key in keys if key not in metadata]:
        raise _not_one(path, writer, f"no {missing} in its metadata")
    return metadata, tensors


def _not_one(path, writer: str, why) -> InvalidInputError:
    return InvalidInputError(f"{path} is not a file that {writer} writes: {why}")
