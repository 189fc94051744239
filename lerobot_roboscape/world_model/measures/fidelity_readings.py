"""The fidelity report's readings as values (what `fidelity.evaluate_fidelity` writes into fidelity.json): the open
loop's measures per step, and the controllability summaries it holds (`controllability.evaluate_controllability`'s,
at the fidelity horizon and the longer one). Reports written before a measure existed read it as None."""

from dataclasses import dataclass, field

import numpy as np

from lerobot_roboscape.io.records import from_record


@dataclass(frozen=True)
class RegionReading:
    """Retrieval of each rollout's own future in one region (whole frame or the object's), over `starts`."""

    retrieval: float
    starts: int | None = None
    own_future_psnr: float | None = None
    other_futures_psnr: float | None = None


@dataclass(frozen=True)
class ArmReading:
    """The arm's measures over starts (`arm_measures.summarise_arm`)."""

    arm_psnr: float | None = None
    arm_psnr_tokenizer: float | None = None
    motion_ratio: float | None = None
    retrieval_state: float | None = None
    tcp_error_cm: float | None = None
    tcp_error_share_of_moved: float | None = None
    scene_psnr_in_window: float | None = None
    scene_psnr_past_window: float | None = None
    arm_psnr_past_window: float | None = None


@dataclass(frozen=True)
class ControlReading:
    """A controllability summary: per region, the retrieval of the model's rollouts and of one ignoring the actions;
    the action gain (dB), the retrieval by likelihood, and the arm's measures."""

    world_model: dict[str, RegionReading]
    ignoring_actions: dict[str, RegionReading] = field(default_factory=dict)
    action_gain_db: float | None = None
    likelihood_retrieval: float | None = None
    arm: ArmReading = ArmReading()

    @property
    def whole_frame(self) -> RegionReading | None:
        return self.world_model.get("whole_frame")

    @property
    def object(self) -> RegionReading | None:
        """None where no start showed the object."""
        return self.world_model.get("object")

    @property
    def whole_frame_ignoring_actions(self) -> RegionReading | None:
        return self.ignoring_actions.get("whole_frame")

    @classmethod
    def from_json(cls, data: dict | None) -> "ControlReading | None":
        return from_record(cls, data) if data else None


@dataclass(frozen=True)
class FidelityReadings:
    """The open loop's per-step means ({"prediction_psnr": [...], "reconstruction_psnr": [...], ...}) over `horizon`
    control steps, and the controllability readings at that horizon and at `long_horizon` (None where not read)."""

    horizon: int
    per_step: dict[str, list[float | None]]
    control: ControlReading | None = None
    long_horizon: int | None = None
    control_long: ControlReading | None = None
    prompt_frames: int | None = None

    def mean_over_steps(self, key: str) -> float | None:
        """The mean of `key` over the steps that measured it (None where none did)."""
        values = [v for v in self.per_step.get(key, []) if v is not None]
        return float(np.mean(values)) if values else None

    @classmethod
    def from_json(cls, data: "dict | FidelityReadings") -> "FidelityReadings":
        if isinstance(data, FidelityReadings):
            return data
        config = data["config"]
        return cls(
            config["horizon"],
            data.get("per_step", {}),
            ControlReading.from_json(data.get("controllability")),
            config.get("long_horizon"),
            ControlReading.from_json(data.get("controllability_long")),
            data.get("prompt_frames"),
        )
