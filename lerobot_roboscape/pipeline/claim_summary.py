"""What the claim experiment measured, as one value: Table 1 and its differences, the ablations, the PPO runs and
their curves, the replays, the targets. Written to the report's results.json and read back from it (results written
before a field existed read with its empty value), so that the report and the README render from either."""

import dataclasses
from dataclasses import dataclass, field

from lerobot_roboscape.evaluation.results import Difference, Results
from lerobot_roboscape.pipeline.replay import Replay

# Fields results.json leaves out when empty (a protocol without them).
OPTIONAL = ("world_model_runs", "other_protocol")


@dataclass
class ClaimSummary:
    """protocol: "paper" or "all-scene"; table: Table 1 (the methods every split runs); differences: PPO in the world
    model minus each other method; reward_ablation and levers: their methods' cells; ppo_runs: what each PPO run
    did in its budget; curve and lever_curves: the world-model runs' checkpoint curves of simulator success;
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
    ppo_runs: list[dict]
    curve: list[dict]
    replays: list[Replay]
    seconds: dict[str, float]
    protocol: str = "all-scene"
    levers: Results = field(default_factory=lambda: Results({}))
    lever_curves: dict[str, list[dict]] = field(default_factory=dict)
    lever_settings: dict[str, str] = field(default_factory=dict)
    world_model_runs: dict | None = None
    other_protocol: dict | None = None

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
            "ppo_runs": self.ppo_runs,
            "curve": self.curve,
            "lever_curves": self.lever_curves,
            "lever_settings": self.lever_settings,
            "replays": [dataclasses.asdict(r) for r in self.replays],
            "seconds": self.seconds,
        }
        return data | {name: getattr(self, name) for name in OPTIONAL if getattr(self, name) is not None}

    def by_comparison(self) -> dict[tuple[str, str, str, str], Difference]:
        """The differences by (policy, against, split, family)."""
        return {d.key: d for d in self.differences}
