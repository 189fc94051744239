"""What the claim experiment measured, as one value: Table 1 and its differences, the ablations, the PPO runs and
their curves, the replays, the targets. Written to the report's results.json and read back from it (results written
before a field existed read with its empty value), so that the report and the README render from either."""

from dataclasses import dataclass, field

from lerobot_roboscape.evaluation.results import Difference, Results
from lerobot_roboscape.experiments.replay import Replay
from lerobot_roboscape.io.records import OMIT_EMPTY, from_record, to_record


@dataclass(frozen=True)
class PpoRun:
    """What one PPO run did in its budget: its iterations, PPO's clock, decisions, the first and last iterations'
    return and success in its own env, its wall-clock with its setup, the simulator steps that ran beside it (the
    done refresh's) and, where an ensemble guarded it, the disagreement at its first and last iterations (each left
    out of the JSON when empty: a run without them, or results written before they existed)."""

    policy: str
    method: str
    iterations: int
    ppo_seconds: float
    decisions: int
    first_return: float
    last_return: float
    first_success: float
    last_success: float
    wall_seconds: float | None
    simulator_steps_beside_ppo: int | None = field(default=None, metadata=OMIT_EMPTY)
    first_disagreement: float | None = field(default=None, metadata=OMIT_EMPTY)
    last_disagreement: float | None = field(default=None, metadata=OMIT_EMPTY)
    last_halted: float | None = field(default=None, metadata=OMIT_EMPTY)


@dataclass(frozen=True)
class WorldModelRunsRecord:
    """Where the runs in the world model ran, when elsewhere (--world_model_runs): the folder they came back to, its
    GPU, the done threshold chosen there, PPO's budget there and the goals' file."""

    folder: str
    gpu: str | None
    done: dict
    time_budget_s: float | None
    goals: str


@dataclass(frozen=True)
class OtherProtocol:
    """The other protocol's Table 1 on the same run."""

    protocol: str
    table: Results


@dataclass(kw_only=True)
class ClaimSummary:
    """protocol: "paper" or "all-scene"; table: Table 1 (the methods every split runs); differences: PPO in the world
    model minus each other method; reward_ablation and levers: their methods' cells; ppo_runs: what each PPO run
    did in its budget; curve and lever_curves: the world-model runs' checkpoint curves of simulator success, and
    baseline_curves the runs' in the simulator, on the same clock;
    lever_settings: each lever's description; replays: the world-model policy's rollouts replayed in the simulator,
    and lever_replays each lever's;
    seconds: each step's; world_model_runs: where the world-model runs ran when elsewhere; other_protocol: the other
    protocol's Table 1 on the same run. The fields are in results.json's order; those marked OMIT_EMPTY are left out
    of it when empty (none in the reports made before they existed)."""

    protocol: str = "all-scene"
    scale: str
    families: list[str]
    date: str
    machine: str
    sft_checkpoint: str | None
    targets: dict
    table: Results
    differences: list[Difference]
    reward_ablation: Results
    levers: Results = field(default_factory=lambda: Results({}))
    ppo_runs: list[PpoRun]
    curve: list[dict]
    lever_curves: dict[str, list[dict]] = field(default_factory=dict)
    lever_settings: dict[str, str] = field(default_factory=dict)
    replays: list[Replay]
    lever_replays: dict[str, list[Replay]] = field(default_factory=dict, metadata=OMIT_EMPTY)
    seconds: dict[str, float]
    baseline_curves: dict[str, list[dict]] = field(default_factory=dict, metadata=OMIT_EMPTY)
    world_model_runs: WorldModelRunsRecord | None = field(default=None, metadata=OMIT_EMPTY)
    other_protocol: OtherProtocol | None = field(default=None, metadata=OMIT_EMPTY)

    @classmethod
    def from_json(cls, data: "dict | ClaimSummary") -> "ClaimSummary":
        return data if isinstance(data, ClaimSummary) else from_record(cls, data)

    def to_json(self) -> dict:
        return to_record(self)

    def by_comparison(self) -> dict[tuple[str, str, str, str], Difference]:
        """The differences by (policy, against, split, family)."""
        return {d.key: d for d in self.differences}
