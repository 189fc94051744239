"""The reward report's readings as values (what `reward_report.write_reward_report` writes into reward_report.json):
how well each reward's return separates successful held-out episodes from failed ones, and how the text model's goals
did."""

from dataclasses import dataclass, fields


@dataclass(frozen=True)
class ReturnReading:
    """One reward's return on the held-out episodes: its ROC-AUC for success (None with one class only) and its mean
    on each class."""

    roc_auc_of_return: float | None
    mean_return_success: float | None = None
    mean_return_failure: float | None = None


@dataclass(frozen=True)
class GoalReadings:
    """The goals' shares: reached done within the family's horizon (of every start), nearer the real final frame than
    the start, and nearer their own instruction's goal than another family's (of the successful episodes)."""

    starts: int
    reached_within_horizon: float
    successful_starts: int
    nearer_final_than_start: float | None
    final_nearer_own_goal_than_other_instructions: float | None = None


@dataclass(frozen=True)
class RewardReadings:
    """Per reward (the world model's, its dense term, the baselines), its return's reading; the goals'; and the
    similarity and done signal the world model's reward was made with."""

    returns: dict[str, ReturnReading]
    goals: GoalReadings | None  # None in a report on episodes without goals
    similarity: str
    done_source: str
    theta: float

    @property
    def world_model(self) -> ReturnReading:
        """The world model's reward: the dense similarity to the goal and the sparse done."""
        return self.returns["world_model"]

    @property
    def dense(self) -> ReturnReading:
        """The dense term alone."""
        return self.returns["world_model_dense"]

    @classmethod
    def from_json(cls, data: "dict | RewardReadings") -> "RewardReadings":
        if isinstance(data, RewardReadings):
            return data
        goal_fields = {f.name for f in fields(GoalReadings)}
        return cls(
            {kind: ReturnReading(**reading) for kind, reading in data["summary"].items()},
            GoalReadings(**{k: v for k, v in data["goals"].items() if k in goal_fields}) if "goals" in data else None,
            data["similarity"],
            data["done_source"],
            data["theta"],
        )
