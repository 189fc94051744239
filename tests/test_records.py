"""A dataclass record read from and written to its JSON by its fields' types (lerobot_roboscape/io/records.py)."""

import json
from dataclasses import dataclass, field
from pathlib import Path

from lerobot_roboscape.evaluation.results import Cell, Results
from lerobot_roboscape.io.records import OMIT_EMPTY, from_record, to_record


@dataclass(frozen=True)
class Inner:
    name: str
    interval: tuple[float, float]


@dataclass
class Outer:
    folder: Path
    inners: list[Inner]
    by_tag: dict[str, Inner]
    table: Results
    best: Inner | None = None
    extra: dict = field(default_factory=dict, metadata=OMIT_EMPTY)
    note: str | None = field(default=None, metadata=OMIT_EMPTY)


def test_a_record_round_trips_through_json_with_its_types():
    cell = Cell.of([True, False, True])
    outer = Outer(
        Path("rl/plain"),
        [Inner("a", (0.1, 0.9))],
        {"t": Inner("b", (0.2, 0.3))},
        Results({"mlp": {"SFT": {"ind": {"all": cell}}}}),
        note="kept",
    )
    data = json.loads(json.dumps(to_record(outer)))
    assert list(data) == ["folder", "inners", "by_tag", "table", "best", "note"]  # field order; empty extra left out
    assert data["folder"] == "rl/plain" and data["inners"] == [{"name": "a", "interval": [0.1, 0.9]}]
    assert data["best"] is None  # None is written unless the field is marked OMIT_EMPTY
    back = from_record(Outer, data)
    assert back.folder == Path("rl/plain") and back.inners == outer.inners and back.by_tag == outer.by_tag
    assert isinstance(back.inners[0].interval, tuple) and back.extra == {} and back.note == "kept"
    assert back.table.cell("mlp", "SFT", "ind") == cell  # a class with its own from_json reads itself


def test_keys_a_record_lacks_are_ignored_and_missing_fields_take_their_defaults():
    data = {"folder": "x", "inners": [], "by_tag": {}, "table": {}, "best": {"name": "c", "interval": [0, 1]}}
    back = from_record(Outer, data | {"written_by_a_later_version": 1})
    assert back.best == Inner("c", (0, 1)) and back.note is None and back.extra == {}
