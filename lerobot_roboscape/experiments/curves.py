"""The checkpoint curves of a protocol's PPO runs: the simulator success (OOD) of the SFT checkpoint and of the
checkpoints each run saved along PPO's clock, on initial states apart from Table 1's."""

from dataclasses import dataclass, field
from pathlib import Path

from lerobot.configs.default import DatasetConfig

from lerobot_roboscape.evaluation.results import ALL, CurvePoint
from lerobot_roboscape.evaluation.success_rate import read_cells
from lerobot_roboscape.pipeline import layout, methods, policy_stages
from lerobot_roboscape.pipeline.methods import Method
from lerobot_roboscape.rl.ppo_state import checkpoint_seconds
from lerobot_roboscape.training.checkpoints import FINAL, spread_checkpoints

CURVE_SEED = 200_000  # the curve's initial states, apart from Table 1's (EvalConfig's default seed)


@dataclass(frozen=True)
class Curves:
    """The checkpoint curves of simulator success (OOD) of a protocol's PPO runs: the plain run in the world model,
    each lever's ({method: curve}) and the runs in the simulator's ({method: curve})."""

    world_model: list[dict]
    levers: dict[str, list[dict]] = field(default_factory=dict)
    baselines: dict[str, list[dict]] = field(default_factory=dict)


def checkpoint_curves(
    cfg, out: Path, demonstrations: DatasetConfig, policy: str, sft: Path, runs: list[str]
) -> dict[str, list[dict]]:
    """Per PPO run (by method) of the experiment `cfg` (its pipeline, curve_points and curve_episodes): OOD
    simulator success of the SFT checkpoint (iteration 0) and of `curve_points` - 1 checkpoints the run saved
    (evenly spread, its last among them), `curve_episodes` per family, on initial states apart from Table 1's:
    {method: [{iteration, seconds, cell}]}. Every point is evaluated in one pass, on the same simulator envs."""
    points = {}
    for method in runs:
        saved = spread_checkpoints(out / layout.rl_dir(policy, method), cfg.curve_points - 1)
        checkpoints = [(0, 0.0, sft), *((int(f.name), checkpoint_seconds(f), f / FINAL) for f in saved)]
        points[method] = [
            (
                iteration,
                seconds,
                policy_stages.eval_job(
                    cfg.pipeline,
                    demonstrations,
                    path,
                    ("ood",),
                    # the SFT checkpoint's point (iteration 0) is every run's: evaluated once, in the plain run's folder
                    out / layout.CURVE_DIR / policy / (curve_tag(method) if iteration else "") / f"{iteration:08d}",
                    episodes=cfg.curve_episodes,
                    seed=CURVE_SEED,
                    videos=0,
                ),
            )
            for iteration, seconds, path in checkpoints
        ]
    jobs = {job.output_dir: job for run in points.values() for _, _, job in run}  # the SFT point's once
    policy_stages.run_evaluations(cfg.pipeline, list(jobs.values()))
    return {
        method: [
            CurvePoint(iteration, seconds, read_cells(job.output_dir, "ood")[ALL]).to_json()
            for iteration, seconds, job in run
        ]
        for method, run in points.items()
    }


def curve_tag(method: str) -> str:
    """The folder of a method's checkpoint curve (PPO in the world model's: the curve folder itself, as before)."""
    return "" if method == methods.RL_WORLD_MODEL else Method.named(method).tag
