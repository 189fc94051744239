"""The done report's readings as values (what `done_report.evaluate_done` writes into done_report.json): per source
of the done signal, its threshold and, per way of reading the episodes, the ROC-AUCs and the episodes it called done
at that threshold."""

from dataclasses import dataclass

from lerobot_roboscape.io.records import from_record

MODES = ("teacher_forced", "open_loop")


@dataclass(frozen=True)
class Confusion:
    """Episodes by outcome and by whether their best done score reached the threshold."""

    success_called_done: int
    success_missed: int
    failed_called_done: int
    failed_not_done: int
    failed_called_done_rate: float | None  # None without failed episodes

    @property
    def successful(self) -> int:
        return self.success_called_done + self.success_missed

    @property
    def failed(self) -> int:
        return self.failed_called_done + self.failed_not_done


@dataclass(frozen=True)
class DoneReading:
    """One source read one way over a set of episodes: frame and episode ROC-AUCs, the confusion at the threshold
    (None where no threshold applied), and the counts of episodes and frames (None where a report left them out)."""

    frame_roc_auc: float | None
    episode_roc_auc: float | None
    confusion: Confusion | None = None
    episodes: int | None = None
    successful: int | None = None
    frames: int | None = None
    done_frames: int | None = None

    @classmethod
    def from_json(cls, data: dict | None) -> "DoneReading | None":
        return None if data is None else from_record(cls, data)


@dataclass(frozen=True)
class SourceReport:
    """A done source (the world model's head, or a success classifier): its threshold, where it came from, and its
    readings on the validation and held-out episodes (None where a mode was not read)."""

    teacher_forced: DoneReading | None
    open_loop: DoneReading | None
    theta: float | None = None
    theta_from: str | None = None
    validation: DoneReading | None = None

    def reading(self, mode: str) -> DoneReading | None:
        return getattr(self, mode)


@dataclass(frozen=True)
class DoneReport:
    """The source the env trusts (the best on the validation episodes) and its threshold, and every source's
    report."""

    source: str
    theta: float
    sources: dict[str, SourceReport]

    @property
    def chosen(self) -> SourceReport:
        return self.sources[self.source]

    def choice(self) -> dict:
        """The report's choice as its JSON keeps it: the source, its threshold and where the threshold came from."""
        return {"source": self.source, "theta": self.theta, "theta_from": self.chosen.theta_from}

    @classmethod
    def from_json(cls, data: dict) -> "DoneReport":
        sources = {name: from_record(SourceReport, report) for name, report in data["sources"].items()}
        chosen = data["chosen"]
        return cls(chosen["source"], float(chosen["theta"]), sources)
