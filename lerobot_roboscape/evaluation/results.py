"""Success in the simulator as values. A `Cell` is one checkpoint's episodes in one split and task family: its
successes, the rate, the rate's 95% Wilson interval and, where kept, each episode's outcome in the order of its
initial state (so that two methods run from the same states compare pair by pair). `Results` are Table 1's cells by
policy, method, split and family. Both read and write the JSON the evaluations write, byte for byte."""

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass

from roboscape_core.errors import InvalidInputError

# A table's splits, in the order of its columns. "scene": the one scene the policy learned, with new initial states
# (the paper's IND under its protocol, section 8.1); "ind": the training scenes with new initial states; "ood": the
# held-out scenes.
SCENE = "scene"
SPLITS = (SCENE, "ind", "ood")
ALL = "all"  # the cell over every family's episodes


def wilson_interval(successes: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """95% Wilson score interval of a success rate (sensible at 0 and n successes, unlike the normal one)."""
    if n == 0:
        return 0.0, 1.0
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return max(0.0, centre - half), min(1.0, centre + half)


def difference_interval(a: "Cell | dict", b: "Cell | dict") -> tuple[float, float, float]:
    """Success rate of cell `a` minus that of cell `b` (independent episodes), with its 95% interval by Newcombe's
    hybrid score method (from the two Wilson intervals): (difference, low, high)."""
    a, b = Cell.from_json(a), Cell.from_json(b)
    pa, pb = a.successes / a.episodes, b.successes / b.episodes
    (la, ua), (lb, ub) = wilson_interval(a.successes, a.episodes), wilson_interval(b.successes, b.episodes)
    d = pa - pb
    return d, d - math.sqrt((pa - la) ** 2 + (ub - pb) ** 2), d + math.sqrt((ua - pa) ** 2 + (pb - lb) ** 2)


def paired_difference_interval(a: list[bool], b: list[bool]) -> tuple[float, float, float]:
    """Success rate of `a` minus that of `b` where episode i of each ran from the same initial state, with its 95%
    interval by Newcombe's square-and-add method for paired proportions (his method 10, 1998: the two Wilson
    intervals joined through the correlation of the pairs, which is what makes it narrower than the unpaired one
    when both methods succeed and fail on the same starts): (difference, low, high)."""
    if len(a) != len(b) or not a:
        raise InvalidInputError(f"paired outcomes need the same episodes on both sides, got {len(a)} and {len(b)}")
    n = len(a)
    both = sum(x and y for x, y in zip(a, b, strict=True))
    only_a = sum(x and not y for x, y in zip(a, b, strict=True))
    only_b = sum(y and not x for x, y in zip(a, b, strict=True))
    neither = n - both - only_a - only_b
    pa, pb = (both + only_a) / n, (both + only_b) / n
    (la, ua), (lb, ub) = wilson_interval(both + only_a, n), wilson_interval(both + only_b, n)
    margins = (both + only_a) * (only_b + neither) * (both + only_b) * (only_a + neither)
    cross = both * neither - only_a * only_b
    # The correlation of the pairs with Newcombe's continuity correction (0 when a margin is empty).
    corrected = cross - n / 2 if cross > n / 2 else min(cross, 0)
    phi = corrected / math.sqrt(margins) if margins else 0.0
    d = pa - pb
    low = d - math.sqrt(max(0.0, (pa - la) ** 2 - 2 * phi * (pa - la) * (ub - pb) + (ub - pb) ** 2))
    high = d + math.sqrt(max(0.0, (ua - pa) ** 2 - 2 * phi * (ua - pa) * (pb - lb) + (pb - lb) ** 2))
    return d, low, high


def paired_interval(ours: "Cell | dict", theirs: "Cell | dict") -> tuple[float, float, float] | None:
    """The paired difference of two cells run on the same initial states, from their episodes' outcomes; None
    for cells written before outcomes were kept."""
    ours, theirs = Cell.from_json(ours), Cell.from_json(theirs)
    if ours.outcomes is None or theirs.outcomes is None:
        return None
    return paired_difference_interval([bool(x) for x in ours.outcomes], [bool(x) for x in theirs.outcomes])


@dataclass(frozen=True)
class Cell:
    success_rate: float
    successes: int
    episodes: int
    ci95: tuple[float, float]
    outcomes: tuple[int, ...] | None = None  # None: written before outcomes were kept

    @classmethod
    def of(cls, outcomes: list[bool]) -> "Cell":
        n, successes = len(outcomes), int(sum(outcomes))
        low, high = wilson_interval(successes, n)
        rate = successes / n if n else 0.0
        return cls(rate, successes, n, (round(low, 4), round(high, 4)), tuple(int(x) for x in outcomes))

    @classmethod
    def from_json(cls, data: dict) -> "Cell":
        if isinstance(data, Cell):
            return data
        outcomes = data.get("outcomes")
        return cls(
            data["success_rate"],
            data["successes"],
            data["episodes"],
            tuple(data["ci95"]),
            None if outcomes is None else tuple(outcomes),
        )

    def to_json(self) -> dict:
        data = {
            "success_rate": self.success_rate,
            "successes": self.successes,
            "episodes": self.episodes,
            "ci95": list(self.ci95),
        }
        return data if self.outcomes is None else data | {"outcomes": list(self.outcomes)}

    def __str__(self) -> str:
        low, high = self.ci95
        return f"{self.successes}/{self.episodes}, 95% CI {low:.2f}-{high:.2f}"


@dataclass(frozen=True)
class CurvePoint:
    """One checkpoint of a PPO run judged in the simulator: its iteration (0: the SFT checkpoint), PPO's clock when
    it was saved (s) and its cell. Written as one JSON object (the cell's fields beside the two)."""

    iteration: int
    seconds: float
    cell: Cell

    @classmethod
    def from_json(cls, data: "dict | CurvePoint") -> "CurvePoint":
        return data if isinstance(data, CurvePoint) else cls(data["iteration"], data["seconds"], Cell.from_json(data))

    def to_json(self) -> dict:
        return {"iteration": self.iteration, "seconds": self.seconds, **self.cell.to_json()}


def curve_of(points: list) -> list[CurvePoint]:
    """A checkpoint curve as points, from its JSON form or as it is."""
    return [CurvePoint.from_json(point) for point in points]


class Results:
    """Table 1's cells: {policy: {method: {split: {family (and "all"): Cell}}}}, in the order they were run."""

    def __init__(self, cells: dict[str, dict[str, dict[str, dict[str, Cell]]]]):
        self.cells = cells

    @classmethod
    def of(cls, table: "Results | dict") -> "Results":
        """`table` as Results: itself, or the JSON form (plain dicts of cells) read into cells."""
        if isinstance(table, Results):
            return table
        return cls(
            {
                policy: {
                    method: {split: {f: Cell.from_json(c) for f, c in cells.items()} for split, cells in splits.items()}
                    for method, splits in methods.items()
                }
                for policy, methods in table.items()
            }
        )

    from_json = of  # its JSON form is what `of` reads

    def to_json(self) -> dict:
        return {
            policy: {
                method: {split: {f: c.to_json() for f, c in cells.items()} for split, cells in splits.items()}
                for method, splits in methods.items()
            }
            for policy, methods in self.cells.items()
        }

    def cell(self, policy: str, method: str, split: str, family: str = ALL) -> Cell:
        try:
            return self.cells[policy][method][split][family]
        except KeyError as error:
            raise InvalidInputError(
                f"no cell for policy {policy!r}, method {method!r}, split {split!r}, family {family!r} in these "
                f"results (methods of {policy!r}: {list(self.cells.get(policy, {}))})"
            ) from error

    def has(self, policy: str, method: str) -> bool:
        return method in self.cells.get(policy, {})

    @property
    def policies(self) -> list[str]:
        return list(self.cells)

    def methods(self, policy: str) -> list[str]:
        return list(self.cells[policy])

    def splits(self) -> list[str]:
        """The splits every method was evaluated in, in column order."""
        held = [set(splits) for methods in self.cells.values() for splits in methods.values()]
        return [split for split in SPLITS if all(split in h for h in held)]

    def where(self, keep: Callable[[str], bool]) -> "Results":
        """The methods `keep` says yes to, under every policy (an empty policy stays, as a table row group)."""
        return Results({p: {m: s for m, s in methods.items() if keep(m)} for p, methods in self.cells.items()})

    def family_cells(self) -> Iterator[Cell]:
        """Every per-family cell (not the "all" cells)."""
        for methods in self.cells.values():
            for splits in methods.values():
                for cells in splits.values():
                    yield from (cell for family, cell in cells.items() if family != ALL)

    def __eq__(self, other) -> bool:
        return isinstance(other, Results) and self.cells == other.cells

    def __bool__(self) -> bool:
        return any(self.cells.values())


@dataclass(frozen=True)
class Difference:
    """One method's success minus another's (`against`) in a (policy, split, family) cell, with Newcombe's 95%
    interval for independent proportions and, where every episode pairs with one from the same initial state, his
    interval for paired proportions, which then decides."""

    policy: str
    against: str
    split: str
    family: str
    difference: float
    ci95: tuple[float, float]
    paired_ci95: tuple[float, float] | None = None

    @classmethod
    def between(cls, ours: Cell, theirs: Cell, policy: str, against: str, split: str, family: str) -> "Difference":
        """`ours` minus `theirs`, with the paired interval where both cells kept their episodes' outcomes (then they
        ran on the same initial states)."""
        d, low, high = difference_interval(ours, theirs)
        paired = paired_interval(ours, theirs)
        paired = paired and (round(paired[1], 4), round(paired[2], 4))
        return cls(policy, against, split, family, round(d, 4), (round(low, 4), round(high, 4)), paired)

    @property
    def key(self) -> tuple[str, str, str, str]:
        return self.policy, self.against, self.split, self.family

    @property
    def interval(self) -> tuple[float, float]:
        """The interval that decides: the paired one where kept."""
        return self.paired_ci95 or self.ci95

    @property
    def kind(self) -> str:
        return "paired" if self.paired_ci95 else "unpaired"

    @classmethod
    def from_json(cls, data: "dict | Difference") -> "Difference":
        if isinstance(data, Difference):
            return data
        paired = data.get("paired_ci95")  # absent from results written before paired intervals
        return cls(
            data["policy"],
            data["against"],
            data["split"],
            data["family"],
            data["difference"],
            tuple(data["ci95"]),
            tuple(paired) if paired else None,
        )

    def to_json(self) -> dict:
        return {
            "policy": self.policy,
            "against": self.against,
            "split": self.split,
            "family": self.family,
            "difference": self.difference,
            "ci95": list(self.ci95),
            "paired_ci95": list(self.paired_ci95) if self.paired_ci95 else None,
        }
