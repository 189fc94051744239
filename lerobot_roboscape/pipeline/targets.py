"""What counts as success: every target of the project's experiments, its threshold and the rule that decides
it, from the reports the stages wrote (the tokenizer's, the world models', SFT's, the agreement with the
simulator's, and the claim's Table 1). A target row is {"value", "goal", "met"} and, where it helps, "detail"."""

from typing import TYPE_CHECKING

from lerobot_roboscape.evaluation.results import (
    ALL,
    Cell,
    Results,
    curve_of,
    difference_interval,
    paired_interval,
)
from lerobot_roboscape.evaluation.tables import SHORT, SPLIT_NAMES
from lerobot_roboscape.pipeline.methods import (
    RL_MANISKILL,
    RL_MANISKILL_ONE_SCENE,
    RL_WORLD_MODEL,
    SFT,
    Method,
)
from lerobot_roboscape.pipeline.target_row import target_row
from lerobot_roboscape.tokenizer.report import view_readings

if TYPE_CHECKING:  # the claim's records, whose modules reach the simulator and the world models
    from lerobot_roboscape.pipeline.claim_summary import PpoRun
    from lerobot_roboscape.pipeline.replay import Replay

# The tokenizer's, on held-out OOD frames, each view (issue 26): the object must survive where it covers >= 4 px.
TOKENIZER_OBJECT_SURVIVAL = 0.95
TOKENIZER_OBJECT_PSNR_DB = 20.0
TOKENIZER_PSNR_DB = 27.0
# SFT, in domain, per family (issue 27): a policy PPO can improve must already succeed sometimes.
SFT_IND_SUCCESS = {"push": 0.6, "pick_place": 0.15}
# The signal PPO gets in the world model (issue 72): its done fires in a share of the episodes by the end of the
# run (there, an episode's success), and the successes it calls are the simulator's too.
DONE_FIRED_SHARE = 0.2
REPLAYED_SUCCESS_SHARE = 0.6


def tokenizer_targets(report: dict) -> dict:
    """The tokenizer's targets, one row per view, from its report on the held-out frames."""
    targets = {}
    for view, m in view_readings(report).items():
        survival, object_psnr, picture = m.object_survival, m.object_psnr, m.picture_object_survives
        targets |= {
            f"tokenizer object survival, {view} (share of held-out frames with the object >= 4 px)": target_row(
                survival,
                f">= {TOKENIZER_OBJECT_SURVIVAL}",
                survival is not None and survival >= TOKENIZER_OBJECT_SURVIVAL,
            ),
            f"tokenizer object-region PSNR, {view} (dB)": target_row(
                object_psnr,
                f">= {TOKENIZER_OBJECT_PSNR_DB:g}",
                object_psnr is not None and object_psnr >= TOKENIZER_OBJECT_PSNR_DB,
            ),
            f"tokenizer reconstruction PSNR, whole frame, {view} (dB)": target_row(
                m.psnr, f">= {TOKENIZER_PSNR_DB:g}", m.psnr >= TOKENIZER_PSNR_DB
            ),
            f"tokenizer object survives in every column of the side-by-side picture, {view}": target_row(
                picture, "all columns", picture is not None and picture == 1.0
            ),
        }
    return targets


def measure_targets(table: Results | dict, families: list[str]) -> dict:
    """{target: {"value", "goal", "met"}} for each policy target of the bench experiment: SFT's, and PPO in the world
    model against the other methods (the world models' are `world_model_targets.py`'s)."""
    targets = {}
    targets |= sft_targets(table, families)
    table = Results.of(table)
    for policy in table.policies:
        if not table.has(policy, RL_WORLD_MODEL):
            continue
        for split in ("ind", "ood"):
            rate = table.cell(policy, RL_WORLD_MODEL, split).success_rate
            for other in (SFT, RL_MANISKILL, RL_MANISKILL_ONE_SCENE):
                if not table.has(policy, other):
                    continue
                theirs = table.cell(policy, other, split).success_rate
                better = rate > theirs if other == SFT else rate >= theirs
                relation = ">" if other == SFT else ">="
                targets[f"{policy} PPO in WM vs {other}, {split.upper()} (all families)"] = target_row(
                    rate, f"{relation} {theirs:.3f}", better
                )
    return targets


def sft_targets(table: Results | dict, families: list[str]) -> dict:
    """The SFT targets, one row per policy and family: in-domain success, its episodes and interval, and the OOD
    success beside it."""
    targets, table = {}, Results.of(table)
    for policy in table.policies:
        for family in families:
            if family not in SFT_IND_SUCCESS:
                continue
            ind, goal = table.cell(policy, SFT, "ind", family), SFT_IND_SUCCESS[family]
            detail = f"IND {ind}"
            if "ood" in table.cells[policy][SFT]:
                ood = table.cell(policy, SFT, "ood", family)
                detail += f"; OOD {ood.success_rate:.3f}, {ood}"
            targets[f"{policy} SFT IND success, {family}"] = target_row(
                ind.success_rate, f">= {goal}", ind.success_rate >= goal, detail
            )
    return targets


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


def signal_targets(runs: "list[PpoRun]", replays: "dict[str, list[Replay]]") -> dict:
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
