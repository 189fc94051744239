"""What counts as success for the paper's claim: PPO in the world model against SFT and PPO in the simulator
(Table 1's cells, decided by their paired intervals), its checkpoint curve, and the signal PPO got in the world
model. A target row is {"value", "goal", "met"} and, where it helps, "detail"."""

from lerobot_roboscape.evaluation.results import ALL, Cell, Results, curve_of, difference_interval, paired_interval
from lerobot_roboscape.evaluation.tables import SHORT, SPLIT_NAMES
from lerobot_roboscape.experiments.claim_summary import PpoRun
from lerobot_roboscape.experiments.replay import Replay
from lerobot_roboscape.pipeline.methods import RL_MANISKILL_ONE_SCENE, RL_WORLD_MODEL, SFT, Method
from lerobot_roboscape.pipeline.report.target_row import target_row

# The signal PPO gets in the world model (issue 72): its done fires in a share of the episodes by the end of the
# run (there, an episode's success), and the successes it calls are the simulator's too.
DONE_FIRED_SHARE = 0.2
REPLAYED_SUCCESS_SHARE = 0.6


def claim_targets(table: Results | dict, families: list[str], curve: list[dict] | None = None) -> dict:
    """The claim's targets, per policy and family: PPO in the world model against SFT out of domain (the 95%
    interval of the difference above 0), against PPO in ManiSkill in one scene out of domain (at least as well),
    and in domain within SFT's interval or above; with the checkpoint `curve` of the world-model run (OOD, from
    SFT at iteration 0), its last checkpoint within the first's interval or above. The paired interval decides
    where both cells hold their episodes (the same initial states for every method), the unpaired one where not."""
    targets, table = {}, Results.of(table)
    trained_in = [split for split in table.splits() if split != "ood"]  # the scenes PPO in the WM met
    for policy in table.policies:
        one_scene = table.has(policy, RL_MANISKILL_ONE_SCENE)
        for family in [*families, ALL]:
            name = SHORT.get(family, family)
            wm, sft = (table.cell(policy, m, "ood", family) for m in (RL_WORLD_MODEL, SFT))
            d, low, high = _deciding_interval(wm, sft)
            targets[f"{policy}, OOD {name}: PPO in WM minus SFT"] = target_row(
                d, "95% interval above 0", low > 0, _intervals(wm, sft)
            )
            if one_scene:
                theirs = table.cell(policy, RL_MANISKILL_ONE_SCENE, "ood", family)
                d, low, high = _deciding_interval(wm, theirs)
                targets[f"{policy}, OOD {name}: PPO in WM minus PPO in ManiSkill (one scene)"] = target_row(
                    d, ">= 0", d >= 0, _intervals(wm, theirs)
                )
            for split in trained_in:
                rate = table.cell(policy, RL_WORLD_MODEL, split, family).success_rate
                floor = table.cell(policy, SFT, split, family).ci95[0]
                targets[f"{policy}, {SPLIT_NAMES[split]} {name}: PPO in WM, within SFT's interval or above"] = (
                    target_row(rate, f">= {floor:.2f} (SFT's 95% lower bound)", rate >= floor)
                )
    if curve:
        first, last = curve_of([curve[0], curve[-1]])
        targets["OOD all: PPO in WM's last checkpoint, within its first's interval or above (checkpoint curve)"] = (
            target_row(
                last.cell.success_rate,
                f">= {first.cell.ci95[0]:.2f} (iteration {first.iteration}'s 95% lower bound)",
                last.cell.success_rate >= first.cell.ci95[0],
                f"iteration {last.iteration}, {last.cell.episodes} episodes",
            )
        )
    return targets


def signal_targets(runs: list[PpoRun], replays: dict[str, list[Replay]]) -> dict:
    """What each PPO run in the world model is told: the share of its last iterations' episodes in which the world
    model's done fired (its success in its own env), and, of its replayed rollouts the world model called
    successes, the share the simulator called successes too (`replays`: by method)."""
    targets = {}
    for run in (r for r in runs if r.method == RL_WORLD_MODEL or r.method in replays):
        targets[f"{run.policy}: {_run_name(run.method)}, episodes the done fired in (last iterations)"] = target_row(
            run.last_success,
            f">= {DONE_FIRED_SHARE}",
            run.last_success >= DONE_FIRED_SHARE,
            f"first iteration {run.first_success:.2f}, iteration {run.iterations} at the end",
        )
    for method, rows in replays.items():
        called = [r for r in rows if r.world_model_success]
        confirmed = sum(r.simulator_success for r in called)
        share = confirmed / len(called) if called else None
        targets[f"{_run_name(method)}: its world-model successes that replay as simulator successes"] = target_row(
            share,
            f">= {REPLAYED_SUCCESS_SHARE}",
            share is not None and share >= REPLAYED_SUCCESS_SHARE,
            f"{confirmed} of {len(called)} world-model successes, {len(rows)} replays",
        )
    return targets


def _run_name(method: str) -> str:
    """A run in the world model as the targets name it: "PPO in WM", and its lever's variant after it."""
    variant = Method.named(method).variant
    return "PPO in WM" + (f", {variant}" if method != RL_WORLD_MODEL and variant else "")


def _deciding_interval(ours: Cell, theirs: Cell) -> tuple[float, float, float]:
    """The difference and the 95% interval that decides a target: paired where both cells kept their episodes."""
    return paired_interval(ours, theirs) or difference_interval(ours, theirs)


def _intervals(ours: Cell, theirs: Cell) -> str:
    """Both 95% intervals of a difference: the unpaired one (Newcombe's hybrid score) and the paired one (where
    known)."""
    _, low, high = difference_interval(ours, theirs)
    text = f"interval [{low:+.2f}, {high:+.2f}]"
    paired = paired_interval(ours, theirs)
    return text if paired is None else text + f"; paired [{paired[1]:+.2f}, {paired[2]:+.2f}]"
