"""Weights read from safetensors only, and only when they fit the model that their config builds.

A pulled or hand-edited repo whose `model.safetensors` misses a tensor, adds one, or holds one of another shape or
dtype is refused with the file and the tensor named, instead of loading half a model (huggingface_hub's and
LeRobot's loaders are not strict by default) or unpickling a `pytorch_model.bin`.
"""

import hashlib
import json
from pathlib import Path

import safetensors.torch
import torch
from huggingface_hub import PyTorchModelHubMixin, constants
from huggingface_hub.errors import EntryNotFoundError, HfHubHTTPError, LocalEntryNotFoundError
from safetensors import safe_open
from torch import nn

from roboscape_core.errors import InvalidInputError, MissingInputError

_SHOWN = 3  # tensors named per kind of fault; the count says how many more
# safetensors' dtype names -> torch's.
_DTYPES = {
    "F32": "float32",
    "F16": "float16",
    "BF16": "bfloat16",
    "F64": "float64",
    "I64": "int64",
    "I32": "int32",
    "I16": "int16",
    "I8": "int8",
    "U8": "uint8",
    "BOOL": "bool",
}


def weights_digest(module: nn.Module, config: dict) -> str:
    """A digest of a model's config and every tensor of its state: what a file made from the model (a token cache,
    a goal bank) records, so that a model retrained in the same folder is not taken for the one it replaced."""
    digest = hashlib.sha256(json.dumps(config, sort_keys=True, default=list).encode())
    for name, tensor in sorted(module.state_dict().items()):
        digest.update(name.encode())
        digest.update(tensor.detach().cpu().contiguous().view(torch.uint8).numpy().tobytes())
    return digest.hexdigest()


def looks_like_repo_id(ref: str) -> bool:
    """`user/name` that is not a local path: a Hub repo id."""
    return ref.count("/") == 1 and not ref.startswith((".", "/", "~")) and not Path(ref).exists()


def check_tensors(model: nn.Module, model_file: str) -> None:
    """Raise InvalidInputError naming `model_file` and the tensors that do not match `model`'s state dict."""
    expected = model.state_dict()
    try:
        with safe_open(str(model_file), framework="pt") as file:
            header = {key: file.get_slice(key) for key in file.keys()}
            found = {key: (tuple(s.get_shape()), s.get_dtype()) for key, s in header.items()}
    except Exception as error:  # safetensors raises its own error types for a truncated or foreign file
        raise InvalidInputError(f"{model_file}: not a readable safetensors file ({error})") from error
    # safetensors stores a tensor shared by several names (tied weights) once, under one of them.
    storage = {}
    for name, tensor in expected.items():
        storage.setdefault(tensor.untyped_storage().data_ptr() if tensor.numel() else name, []).append(name)
    aliases = {name: names for names in storage.values() for name in names}
    faults = []
    missing = [name for name in expected if not any(alias in found for alias in aliases[name])]
    unexpected = [name for name in found if name not in expected]
    wrong = [
        f"{name} {found[name][0]} {found[name][1]}, expected {tuple(expected[name].shape)} "
        f"{str(expected[name].dtype).removeprefix('torch.')}"
        for name in found
        if name in expected and not _fits(found[name], expected[name])
    ]
    for kind, names in (("missing", missing), ("unexpected", unexpected), ("mismatched", wrong)):
        if names:
            more = f" and {len(names) - _SHOWN} more" if len(names) > _SHOWN else ""
            faults.append(f"{kind} tensors {'; '.join(names[:_SHOWN])}{more}")
    if faults:
        raise InvalidInputError(
            f"{model_file} does not fit the {type(model).__name__} its config.json builds: " + ", ".join(faults)
        )


def _fits(found: tuple[tuple, str], tensor) -> bool:
    shape, dtype = found
    return shape == tuple(tensor.shape) and _DTYPES.get(dtype, dtype) == str(tensor.dtype).removeprefix("torch.")


class CheckedHubMixin(PyTorchModelHubMixin):
    """PyTorchModelHubMixin that loads `model.safetensors` strictly, after `check_tensors`, and never unpickles;
    a reference that is neither a model directory nor a reachable Hub repo is a MissingInputError."""

    @classmethod
    def from_pretrained(cls, pretrained_model_name_or_path, **kwargs):
        ref = str(pretrained_model_name_or_path)
        path = Path(ref).expanduser()
        if path.is_dir() and not (path / constants.CONFIG_NAME).is_file():
            raise MissingInputError(f"no {cls.__name__} at {ref}: the directory has no {constants.CONFIG_NAME}")
        if not path.is_dir() and not looks_like_repo_id(ref):
            raise MissingInputError(f"no {cls.__name__} at {ref}: no such directory")
        try:
            return super().from_pretrained(ref, **kwargs)
        except (LocalEntryNotFoundError, EntryNotFoundError, HfHubHTTPError) as error:
            raise MissingInputError(
                f"no {cls.__name__} at {ref}: no such directory, and the Hub repo {ref!r} "
                f"could not be fetched ({type(error).__name__})"
            ) from error

    @classmethod
    def _load_as_safetensor(cls, model, model_file: str, map_location: str, strict: bool):
        check_tensors(model, model_file)
        safetensors.torch.load_model(model, model_file, strict=True, device=map_location)
        return model.eval()

    @classmethod
    def _load_as_pickle(cls, model, model_file: str, map_location: str, strict: bool):
        raise InvalidInputError(
            f"{model_file}: only model.safetensors is read (a pickled file can run code); "
            "convert it with safetensors, or push the model again with roboscape-push"
        )
