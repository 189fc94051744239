"""Errors a user can fix, and the checks that raise them.

A `UserError` is a bad path, a bad flag value, a malformed file, a missing model or a mismatched camera: its
message names the file, episode, frame, key or value at fault and says what to do. The command lines print it as
one line (`cli.one_line_errors`); any other exception is a bug and keeps its traceback. The subclasses are also the
built-in error of their kind, so `except ValueError` still catches an invalid input.
"""

from collections.abc import Callable

import numpy as np


class UserError(Exception):
    """An input the user can fix; its message is the whole report."""


class InvalidInputError(UserError, ValueError):
    """A flag value, file or dataset that is malformed, inconsistent or not finite."""


class MissingInputError(UserError, FileNotFoundError):
    """A path, model, dataset or checkpoint that is not there."""


class OutputExistsError(UserError, FileExistsError):
    """An output that would overwrite earlier work."""


def require_finite(values, where: str, key: str, row_name: Callable[[int], str] = lambda row: f"frame {row}") -> None:
    """Raise InvalidInputError naming `where`, the first bad row (`row_name(row)`, by default its frame) and `key`
    if any value is NaN or infinite."""
    values = np.asarray(values)
    if not np.issubdtype(values.dtype, np.floating):
        return
    bad_rows = ~np.isfinite(values.reshape(len(values), -1)).all(axis=1)
    if bad_rows.any():
        row = int(np.argmax(bad_rows))
        raise InvalidInputError(
            f"{where} {row_name(row)}: {key} is not finite "
            f"({np.array2string(values[row], precision=4)}); {int(bad_rows.sum())} of "
            f"{len(values)} frames are"
        )


def require_shape(values, where: str, key: str, shape: tuple) -> None:
    """Raise InvalidInputError unless `values` has `shape` (None: any size along that axis)."""
    actual = tuple(np.shape(values))
    fits = len(actual) == len(shape) and all(want in (None, got) for got, want in zip(actual, shape, strict=True))
    if not fits:
        expected = "(" + ", ".join("N" if want is None else str(want) for want in shape) + ")"
        raise InvalidInputError(f"{where}: {key} has shape {actual}, expected {expected}")
