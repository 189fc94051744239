"""Numbered stage headers (`=== 3/13 title ===`) and the time each stage took, for the demo and the experiment.
A header is printed when its stage starts, so it also marks where the stage before it completed."""

import time


class StageClock:
    """Numbered stage headers, one per entry of `stages` in their order; records the time each stage took."""

    def __init__(self, stages: tuple[str, ...]):
        self.stages, self.number, self.title, self.start, self.began = stages, 0, None, None, time.time()
        self.seconds: dict[str, float] = {}

    def __call__(self, stage: str, title: str):
        if self.stages[self.number] != stage:
            raise RuntimeError(f"stage {stage!r} runs where the stage list has {self.stages[self.number]!r}")
        self.done()
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
