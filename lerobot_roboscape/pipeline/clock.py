"""Numbered stage headers (`=== 3/13 title ===`) and the time each stage took, for the demo and the experiment.
A header is printed when its stage starts, so it also marks where the stage before it completed."""

import time

from roboscape_core.errors import InvalidInputError


class StopAfter(Exception):  # noqa: N818 (a signal, not an error)
    """The stage a run was asked to stop after is complete."""


class StageClock:
    """Numbered stage headers, one per entry of `stages` in their order; records the time each stage took. With
    `stop_after`, the stage after that one raises StopAfter instead of starting."""

    def __init__(self, stages: tuple[str, ...], stop_after: str | None = None):
        if stop_after is not None and stop_after not in stages:
            raise InvalidInputError(f"stop_after={stop_after!r} is not a stage; the stages are {list(stages)}")
        self.stages, self.number, self.title, self.start, self.began = stages, 0, None, None, time.time()
        self.stop_after = stop_after
        self.seconds: dict[str, float] = {}

    def __call__(self, stage: str, title: str):
        if self.stages[self.number] != stage:
            raise RuntimeError(f"stage {stage!r} runs where the stage list has {self.stages[self.number]!r}")
        self.done()
        if self.number and self.stages[self.number - 1] == self.stop_after:
            print(f"\n=== stopped after stage {self.number}/{len(self.stages)}, {self.stop_after} ===", flush=True)
            raise StopAfter(self.stop_after)
        self.number += 1
        self.title, self.start = title, time.time()
        print(f"\n{header(self.number, len(self.stages))} {title} ===", flush=True)

    def done(self):
        if self.start is not None:
            self.seconds[self.title] = time.time() - self.start
            print(
                f"--- stage {self.number} done in {self.seconds[self.title]:.0f}s "
                f"({(time.time() - self.began) / 60:.1f} min so far)",
                flush=True,
            )
            self.start = None


def header(number: int, total: int) -> str:
    """How stage `number`'s header line begins."""
    return f"=== {number}/{total}"
