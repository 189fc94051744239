"""Dataclass records to and from their JSON, read by the fields' types: nested records, their lists and dicts,
tuples, paths and None where a field is optional. A class with its own `from_json` / `to_json` reads and writes
itself. The JSON's keys are the dataclass's fields, in their order, so a record's field names live in one place."""

import dataclasses
import types
import typing
from pathlib import Path

# Field metadata: the field is left out of the JSON while None or empty (a record written before it existed reads
# back with its default).
OMIT_EMPTY = {"omit_empty": True}


def to_record(record) -> dict:
    """`record` (a dataclass) as JSON: its fields in order, those marked OMIT_EMPTY left out while empty."""
    data = {}
    for f in dataclasses.fields(record):
        value = getattr(record, f.name)
        if f.metadata.get("omit_empty") and (value is None or (isinstance(value, (dict, list, tuple)) and not value)):
            continue
        data[f.name] = _encode(value)
    return data


def from_record(cls, data: dict):
    """A `cls` from its JSON; keys it has no field for are ignored, fields the JSON lacks take their defaults."""
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    return cls(**{k: _decode(hints[k], v) for k, v in data.items() if k in names})


def _encode(value):
    if hasattr(value, "to_json"):
        return value.to_json()
    if dataclasses.is_dataclass(value):
        return to_record(value)
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, dict):
        return {k: _encode(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_encode(v) for v in value]
    return value


def _decode(kind, value):
    if value is None:
        return None
    origin, args = typing.get_origin(kind), typing.get_args(kind)
    if origin in (typing.Union, types.UnionType):  # `X | None`: read as X
        return _decode(next(a for a in args if a is not type(None)), value)
    if origin is list:
        return [_decode(args[0], v) for v in value]
    if origin is tuple:
        return tuple(value) if not args or args[-1] is Ellipsis else tuple(map(_decode, args, value))
    if origin is dict:
        return {k: _decode(args[1], v) for k, v in value.items()}
    if isinstance(kind, type) and hasattr(kind, "from_json"):
        return kind.from_json(value)
    if dataclasses.is_dataclass(kind):
        return from_record(kind, value)
    if kind is Path:
        return Path(value)
    return value
