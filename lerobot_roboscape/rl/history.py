"""PPO's history as its readers see it: one `Iteration` per line of the run's history.jsonl (rl/ppo.py writes the
lines, with CleanRL's `charts/` and `losses/` names), so that no reader outside rl/ spells those names."""

from dataclasses import dataclass
from pathlib import Path

from lerobot_roboscape.training.records import read_history


@dataclass(frozen=True)
class Iteration:
    """One PPO iteration: its number, PPO's clock after it (s), the decisions it collected, the mean return and
    success of the episodes that ended in it (in its own env), and, where an ensemble guarded the run, the
    disagreement per decision (nats) and the share of episodes halted by it. `logs`: the whole line."""

    iteration: int
    seconds: float
    samples: int
    episode_return: float
    success: float
    disagreement: float | None
    halted: float | None
    logs: dict

    @classmethod
    def from_line(cls, line: dict) -> "Iteration":
        return cls(
            iteration=line["iteration"],
            seconds=line["seconds"],
            samples=int(line["charts/samples"]),
            episode_return=line["charts/episode_return"],
            success=line["charts/success"],
            disagreement=line.get("charts/disagreement"),
            halted=line.get("charts/halted"),
            logs=line,
        )


def read_ppo_history(output_dir: str | Path) -> list[Iteration]:
    """The iterations a PPO run logged (none when it has not run)."""
    return [Iteration.from_line(line) for line in read_history(Path(output_dir))]
