"""The agreement ladder's readings as values (what `ladder.ladder_summary` writes into ladder.json): the policies'
success in the simulator beside their return in the world model, the ladder's rank correlation, and the per-episode
agreement of every episode pooled."""

from dataclasses import dataclass


@dataclass(frozen=True)
class AgreementConfusion:
    """Paired episodes by the simulator's outcome (truth) and the world model's."""

    sim_success_wm_success: int
    sim_success_wm_failure: int
    sim_failure_wm_success: int
    sim_failure_wm_failure: int

    @property
    def simulator_successes(self) -> int:
        return self.sim_success_wm_success + self.sim_success_wm_failure

    @property
    def simulator_failures(self) -> int:
        return self.sim_failure_wm_success + self.sim_failure_wm_failure


@dataclass(frozen=True)
class Ladder:
    """Per policy, its simulator success rate and world-model mean return, their Spearman correlation (None with
    fewer than 3 policies or a constant side), and the pooled episodes' balanced accuracy and confusion; whether the
    simulator's 95% intervals tell every rung from the next (None: a ladder written before they were kept); the most
    rungs it tells apart (indices, in order of success) and the Spearman over them (a ladder written before they
    were kept: every rung, where told apart)."""

    policies: list[str]
    simulator_success_rate: list[float]
    world_model_mean_return: list[float]
    spearman_return_vs_success: float | None
    episodes: int
    balanced_accuracy: float | None
    confusion: AgreementConfusion
    told_apart: bool | None = None
    apart_rungs: list[int] | None = None
    apart_spearman: float | None = None

    @classmethod
    def from_json(cls, data: dict) -> "Ladder":
        pooled, rho = data["pooled"], data["spearman_return_vs_success"]
        every = list(range(len(data["policies"]))) if data.get("told_apart") else None
        apart = data.get("apart", {"rungs": every, "spearman_return_vs_success": rho if every else None})
        return cls(
            data["policies"],
            data["simulator_success_rate"],
            data["world_model_mean_return"],
            rho,
            pooled["episodes"],
            pooled["balanced_accuracy"],
            AgreementConfusion(**pooled["confusion"]),
            data.get("told_apart"),
            apart["rungs"],
            apart["spearman_return_vs_success"],
        )
