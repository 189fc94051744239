"""What the claim experiment measured, as one value: Table 1 and its differences, the ablations, the PPO runs and
their curves, the replays, the targets. Written to the report's results.json and read back from it (results written
before a field existed read with its empty value), so that the report and the README render from either."""

import dataclasses
from dataclasses import dataclass, field

from lerobot_roboscape.evaluation.results import Difference, Results
from lerobot_roboscape.pipeline.replay import Replay

# A PPO run's fields results.json leaves out when empty (a run without them, or results written before they existed).
RUN_OPTIONAL = ("simulator_steps_beside_ppo", "first_disagreement", "last_disagreement", "last_halted")


@dataclass(frozen=True)
class PpoRun:
    """What one PPO run did in its budget: its iterations, PPO's clock, decisions, the first and last iterations'
    return and success in its own env, its wall-clock with its setup, the simulator steps that ran beside it (the
    done refresh's) and, where an ensemble guarded it, the disagreement at its first and last iterations."""

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
    simulator_steps_beside_ppo: int | None = None
    first_disagreement: float | None = None
    last_disagreement: float | None = None
    last_halted: float | None = None

    def to_json(self) -> dict:
        return {k: v for k, v in dataclasses.asdict(self).items() if k not in RUN_OPTIONAL or v is not None}


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

    def to_json(self) -> dict:
        return {"protocol": self.protocol, "table": self.table.to_json()}

    @classmethod
    def from_json(cls, data: dict) -> "OtherProtocol":
        return cls(data["protocol"], Results.of(data["table"]))


@dataclass
class ClaimSummary:
    """protocol: "paper" or "all-scene"; table: Table 1 (the methods every split runs); differences: PPO in the world
    model minus each other method; reward_ablation and levers: their methods' cells; ppo_runs: what each PPO run
    did in its budget; curve and lever_curves: the world-model runs' checkpoint curves of simulator success, and
    baseline_curves the runs' in the simulator, on the same clock;
    lever_settings: each lever's description; replays: the world-model policy's rollouts replayed in the simulator;
    seconds: each step's; world_model_runs: where the world-model runs ran when elsewhere; other_protocol: the other
    protocol's Table 1 on the same run."""

    scale: str
    families: list[str]
    date: str
    machine: str
    sft_checkpoint: str | None
    targets: dict
    table: Results
    differences: list[Difference]
    reward_ablation: Results
    ppo_runs: list[PpoRun]
    curve: list[dict]
    replays: list[Replay]
    seconds: dict[str, float]
    protocol: str = "all-scene"
    levers: Results = field(default_factory=lambda: Results({}))
    lever_curves: dict[str, list[dict]] = field(default_factory=dict)
    lever_settings: dict[str, str] = field(default_factory=dict)
    baseline_curves: dict[str, list[dict]] = field(default_factory=dict)
    world_model_runs: WorldModelRunsRecord | None = None
    other_protocol: OtherProtocol | None = None

    @classmethod
    def from_json(cls, data: "dict | ClaimSummary") -> "ClaimSummary":
        if isinstance(data, ClaimSummary):
            return data
        known = {f.name for f in dataclasses.fields(cls)}
        values = {k: v for k, v in data.items() if k in known}
        for name in ("table", "reward_ablation", "levers"):
            if name in values:
                values[name] = Results.of(values[name])
        values["differences"] = [Difference.from_json(d) for d in values["differences"]]
        values["replays"] = [Replay.from_json(r) for r in values["replays"]]
        values["ppo_runs"] = [PpoRun(**r) for r in values["ppo_runs"]]
        if values.get("world_model_runs"):
            values["world_model_runs"] = WorldModelRunsRecord(**values["world_model_runs"])
        if values.get("other_protocol"):
            values["other_protocol"] = OtherProtocol.from_json(values["other_protocol"])
        return cls(**values)

    def to_json(self) -> dict:
        data = {
            "protocol": self.protocol,
            "scale": self.scale,
            "families": self.families,
            "date": self.date,
            "machine": self.machine,
            "sft_checkpoint": self.sft_checkpoint,
            "targets": self.targets,
            "table": self.table.to_json(),
            "differences": [d.to_json() for d in self.differences],
            "reward_ablation": self.reward_ablation.to_json(),
            "levers": self.levers.to_json(),
            "ppo_runs": [r.to_json() for r in self.ppo_runs],
            "curve": self.curve,
            "lever_curves": self.lever_curves,
            "lever_settings": self.lever_settings,
            "replays": [dataclasses.asdict(r) for r in self.replays],
            "seconds": self.seconds,
        }
        if self.baseline_curves:  # none in the reports made before they were drawn
            data["baseline_curves"] = self.baseline_curves
        if self.world_model_runs is not None:
            data["world_model_runs"] = dataclasses.asdict(self.world_model_runs)
        if self.other_protocol is not None:
            data["other_protocol"] = self.other_protocol.to_json()
        return data

    def by_comparison(self) -> dict[tuple[str, str, str, str], Difference]:
        """The differences by (policy, against, split, family)."""
        return {d.key: d for d in self.differences}
