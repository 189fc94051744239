"""What counts as success in a pipeline run: each target, its threshold and the rule that decides it, from the
reports the stages wrote (the tokenizer's, SFT's, PPO's; the claim's are `experiments/claim_targets.py`). A target
row is {"value", "goal", "met"} and, where it helps, "detail"."""

from lerobot_roboscape.evaluation.results import (
    Results,
)
from lerobot_roboscape.pipeline.methods import (
    RL_MANISKILL,
    RL_MANISKILL_ONE_SCENE,
    RL_WORLD_MODEL,
    SFT,
)
from lerobot_roboscape.pipeline.report.target_row import target_row
from lerobot_roboscape.tokenizer.report import view_readings

# The tokenizer's, on held-out OOD frames, each view (issue 26): the object must survive where it covers >= 4 px.
TOKENIZER_OBJECT_SURVIVAL = 0.95
TOKENIZER_OBJECT_PSNR_DB = 20.0
TOKENIZER_PSNR_DB = 27.0
# SFT, in domain, per family (issue 27): a policy PPO can improve must already succeed sometimes.
SFT_IND_SUCCESS = {"push": 0.6, "pick_place": 0.15}


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
