"""The claim's targets (`claim_targets`), cell by cell, on hand-made tables: met, missed, and undecidable (an
interval that straddles 0, a method not run); the differences' intervals; the report's regenerate command."""

import re

import pytest

from lerobot_roboscape.evaluation.results import Cell, Results
from lerobot_roboscape.evaluation.tables import format_table
from lerobot_roboscape.experiments.claim_markdown import command, markdown, paper_methods
from lerobot_roboscape.experiments.claim_summary import ClaimSummary
from lerobot_roboscape.experiments.claim_targets import claim_targets
from lerobot_roboscape.experiments.experiment import ExperimentConfig
from lerobot_roboscape.experiments.experiment_report import differences
from lerobot_roboscape.experiments.levers import LEVERS, KLSettings, LeverSettings, lever_descriptions
from lerobot_roboscape.pipeline.config import DataConfig, PipelineConfig, parse_config, scale_config
from lerobot_roboscape.pipeline.methods import RL_MANISKILL, RL_MANISKILL_ONE_SCENE, RL_WORLD_MODEL, SFT
from roboscape_core.errors import InvalidInputError

RL_WORLD_MODEL_KL, ENSEMBLE = LEVERS["kl"].method, LEVERS["ensemble"].method


def cell(successes: int, episodes: int = 50, first: int = 0) -> dict:
    """`successes` of `episodes` on the same initial states, solved from state `first` on (wrapping round)."""
    outcomes = [(i - first) % episodes < successes for i in range(episodes)]
    return Cell.of(outcomes).to_json()


def table(wm_ood: int, sft_ood: int, wm_ind: int, sft_ind: int, one_scene_ood: int | None) -> dict:
    # Each method solves its own run of states, so a pair of methods shares few successes (the paired interval,
    # which decides, is about as wide as the unpaired one).
    def method(ood, ind, first):
        ood_cell, ind_cell = cell(ood, first=first), cell(ind, first=first)
        return {"ood": {"push": ood_cell, "all": ood_cell}, "ind": {"push": ind_cell, "all": ind_cell}}

    methods = {RL_WORLD_MODEL: method(wm_ood, wm_ind, 0), SFT: method(sft_ood, sft_ind, 25)}
    if one_scene_ood is not None:
        methods[RL_MANISKILL_ONE_SCENE] = method(one_scene_ood, 0, 10)
    return {"mlp": methods}


# (PPO in WM OOD, SFT OOD, PPO in WM IND, SFT IND, PPO in one scene OOD) of 50 -> (vs SFT, vs one scene, IND)
CASES = {
    "all met": ((40, 10, 30, 25, 30), (True, True, True)),
    "all missed": ((10, 25, 5, 30, 20), (False, False, False)),
    "ahead of SFT, interval straddles 0": ((20, 15, 25, 25, 20), (False, True, True)),
    # SFT's 22/50 in domain has the 95% lower bound 0.312: 16/50 (0.32) is within it, 15/50 (0.30) below
    "IND just within SFT's interval": ((40, 10, 16, 22, 40), (True, True, True)),
    "IND just below SFT's interval": ((40, 10, 15, 22, 40), (True, True, False)),
}


@pytest.mark.parametrize("name", CASES)
def test_claim_targets_cells(name):
    counts, expected = CASES[name]
    targets = claim_targets(table(*counts), ["push"])
    met = (
        targets["mlp, OOD Push: PPO in WM minus SFT"]["met"],
        targets["mlp, OOD Push: PPO in WM minus PPO in ManiSkill (one scene)"]["met"],
        targets["mlp, IND Push: PPO in WM, within SFT's interval or above"]["met"],
    )
    assert met == expected
    assert targets["mlp, OOD Push: PPO in WM minus SFT"]["value"] == pytest.approx((counts[0] - counts[1]) / 50)


def test_without_ppo_in_one_scene_its_rows_are_absent_not_missed():
    targets = claim_targets(table(40, 10, 30, 25, None), ["push"])
    assert not any("one scene" in name for name in targets)
    assert len(targets) == 4  # push and all: against SFT OOD, within SFT IND


def test_differences_give_the_paired_interval_beside_the_unpaired():
    # PPO in the WM solves the 30 starts SFT solves and 5 more: unpaired the difference straddles 0, paired not.
    wm = Cell.of([True] * 35 + [False] * 15).to_json()
    sft = Cell.of([True] * 30 + [False] * 20).to_json()
    cells = {"ood": {"push": wm, "all": wm}, "ind": {"push": wm, "all": wm}}
    theirs = {"ood": {"push": sft, "all": sft}, "ind": {"push": sft, "all": sft}}
    rows = differences({"mlp": {RL_WORLD_MODEL: cells, SFT: theirs}}, ["push"])
    row = next(r for r in rows if (r.split, r.family) == ("ood", "push"))
    assert row.difference == pytest.approx(0.1)
    assert row.ci95[0] < 0 < row.paired_ci95[0] and row.interval == row.paired_ci95
    # The paired interval decides the target: the same initial states for every method.
    target = claim_targets({"mlp": {RL_WORLD_MODEL: cells, SFT: theirs}}, ["push"])[
        "mlp, OOD Push: PPO in WM minus SFT"
    ]
    assert target["met"] and "paired [+" in target["detail"]
    # Cells written before the episodes were kept have no paired interval: the unpaired one decides.
    old = {k: v for k, v in sft.items() if k != "outcomes"}
    unpaired = {s: {"push": old, "all": old} for s in theirs}
    rows = differences({"mlp": {RL_WORLD_MODEL: cells, SFT: unpaired}}, ["push"])
    assert all(r.paired_ci95 is None and r.kind == "unpaired" for r in rows)
    target = claim_targets({"mlp": {RL_WORLD_MODEL: cells, SFT: unpaired}}, ["push"])[
        "mlp, OOD Push: PPO in WM minus SFT"
    ]
    assert not target["met"] and "paired" not in target["detail"]


@pytest.mark.parametrize(("first", "last", "met"), [(20, 20, True), (20, 14, True), (20, 13, False), (5, 30, True)])
def test_the_checkpoint_curve_target_holds_the_last_checkpoint_within_the_firsts_interval(first, last, met):
    # 20/50 has the 95% lower bound 0.276: 14/50 (0.28) is within it, 13/50 (0.26) below.
    curve = [{"iteration": i, "seconds": 60.0 * i, **cell(n)} for i, n in ((0, first), (5, 25), (10, last))]
    targets = claim_targets(table(40, 10, 30, 25, None), ["push"], curve)
    (name,) = [n for n in targets if "checkpoint curve" in n]
    assert targets[name]["met"] == met and targets[name]["value"] == pytest.approx(last / 50)


def test_regenerate_command_gives_back_the_same_settings():
    cfg = ExperimentConfig(
        pipeline=scale_config(
            "bench",
            ("--output_dir=outputs/x", "--data.max_scenes=8", "--ppo.time_budget_s=360", "--reward_ablation=false"),
        ),
        protocol="all_scenes",
        sft_checkpoint="outputs/sft/pretrained_model",
        levers=["kl", "branched"],
        lever=LeverSettings(kl=KLSettings(coef=0.3)),
        report_dir="docs/results/x",
        readme=None,
    )
    args = command(cfg).split()[1:]
    assert "--pipeline.data.max_scenes=8" in args and "--pipeline.reward_ablation=false" in args
    assert "--pipeline.ppo.time_budget_s=360" in args and not any("wm_train" in a for a in args)
    assert "--levers=[kl,branched]" in args and "--lever.kl.coef=0.3" in args
    assert parse_config(ExperimentConfig, args, "pipeline.") == cfg
    assert ExperimentConfig().protocol == "paper"  # the paper's protocol unless told otherwise
    with pytest.raises(InvalidInputError, match="--protocol must be one of \\['paper', 'all_scenes'\\], got 'one'"):
        ExperimentConfig(protocol="one")
    with pytest.raises(
        InvalidInputError,
        match=re.escape(f"--levers ['gravity'] unknown; choose from {list(LEVERS)}"),
    ):
        ExperimentConfig(levers=["gravity"])
    with pytest.raises(InvalidInputError, match="--curve_points must be >= 2"):
        ExperimentConfig(curve_points=1)
    with pytest.raises(InvalidInputError, match="--data.initial_scene_episodes must be >= 0, got -1"):
        PipelineConfig(data=DataConfig(initial_scene_episodes=-1))


def test_the_report_says_which_protocol_ran_and_gives_each_lever_its_row_and_curve():
    cfg = ExperimentConfig(pipeline=scale_config("smoke"), levers=["kl", "ensemble"], readme=None)
    results = table(40, 10, 30, 25, 30)
    curve = [{"iteration": i, "seconds": 60.0 * i, **cell(n, 20)} for i, n in ((0, 4), (5, 6), (10, 9))]
    summary = {
        "scale": "smoke",
        "families": ["push"],
        "sft_checkpoint": None,
        "machine": "a test",
        "date": "2026-11-26",
        "table": results,
        "targets": claim_targets(results, ["push"]),
        "differences": differences(results, ["push"]),
        "reward_ablation": {"mlp": {}},
        "levers": {"mlp": {m: {"ood": {"push": cell(12), "all": cell(12)}} for m in (RL_WORLD_MODEL_KL, ENSEMBLE)}},
        "lever_curves": {RL_WORLD_MODEL_KL: curve, ENSEMBLE: curve},
        "lever_settings": lever_descriptions([RL_WORLD_MODEL_KL, ENSEMBLE], cfg.lever),
        "ppo_runs": [
            {"policy": "mlp", "method": ENSEMBLE, "iterations": 9, "ppo_seconds": 60.0, "decisions": 900}
            | {"first_return": 0.1, "last_return": 0.2, "first_success": 0.0, "last_success": 0.1, "wall_seconds": 75.0}
            | {"first_disagreement": 0.012, "last_disagreement": 0.034, "last_halted": 0.25}
        ],
        "curve": curve,
        "replays": [
            {"episode_index": i, "family": "push", "scene": "s", "world_model_return": 1.0, "video": f"{i}.mp4"}
            | {"world_model_success": True, "simulator_success": sim}
            for i, sim in enumerate((True, False, False))
        ],
        "seconds": {},
    }
    text = markdown(cfg, summary)
    assert "The paper's protocol (`--protocol=paper`)" in text and "initial scene only" in text
    # The first lines answer the user's question: 40/50 against SFT's 10/50 OOD, on different initial states.
    lines = text.splitlines()
    first = lines.index("**Does RL in the world model make the policy better out of domain?**")
    assert lines[first + 1].startswith("- **Yes** (mlp): PPO in the world model took the SFT policy from 20% to 80%")
    assert "+60 points, paired 95% interval [+" in lines[first + 1]
    assert lines[first + 2].startswith(f"- Against {RL_MANISKILL_ONE_SCENE} (60% OOD): +20 points, paired")
    assert "outcome of 1 of 3" in lines[first + 3]
    row = next(line for line in text.splitlines() if line.startswith(f"| {RL_WORLD_MODEL_KL} |"))
    assert "12/50 (24% [" in row and "0: 4/20 (20% [" in row and "10: 9/20 (45% [" in row
    assert "| KL to the SFT policy x 0.1 |" in row
    guards = text.split("## Guards against gaming the world model")[1]
    row = next(line for line in guards.splitlines() if line.startswith(f"| {ENSEMBLE} |"))
    assert "2 more (its last 1 block(s) and heads drawn afresh and retrained alone, 25% of its steps each)" in row
    assert "reward - 1.0 x their disagreement |" in row  # no threshold: no halt
    assert f"({ENSEMBLE}), in nats per decision: 0.0120 at its first iteration, 0.0340 over its last 3 (25%" in text
    assert "The other protocol" not in text and "The runs in the simulator" not in text
    # The runs in the simulator's checkpoint curves, where they were drawn: a row each, and kept by results.json.
    baselines = {RL_MANISKILL_ONE_SCENE: curve}
    text = markdown(cfg, summary | {"baseline_curves": baselines})
    row = next(line for line in text.splitlines() if line.startswith(f"| {RL_MANISKILL_ONE_SCENE} | 0.0: "))
    assert "0.0: 4/20 (20% [" in row and "10.0: 9/20 (45% [" in row
    stored = ClaimSummary.from_json(summary | {"baseline_curves": baselines, "protocol": "paper"}).to_json()
    assert stored["baseline_curves"] == baselines
    assert "baseline_curves" not in ClaimSummary.from_json(summary | {"protocol": "paper"}).to_json()
    # The all-scene protocol's report, where the paper protocol's Table 1 was found: both tables.
    cfg = ExperimentConfig(pipeline=scale_config("smoke"), protocol="all_scenes", readme=None)
    other = {"protocol": "paper", "table": table(5, 1, 30, 25, 3)}
    text = markdown(cfg, summary | {"levers": {"mlp": {}}, "lever_curves": {}, "other_protocol": other})
    assert "The all-scene protocol" in text and "Guards against gaming" not in text
    assert "### The other protocol on the same world models (`--protocol=paper`)" in text
    assert "| mlp | RL w. World Model | 60 [46, 72] (26) | 10 [4, 21] (17) |" in text.split("### The other")[1]


def test_the_paper_protocols_scene_column_sits_under_the_papers_ind_and_has_its_own_rows():
    # Under the paper's protocol the table has the scene SFT learned (new initial states) beside IND and OOD.
    results = table(40, 10, 30, 25, 30)
    for method, first in ((RL_WORLD_MODEL, 0), (SFT, 25), (RL_MANISKILL_ONE_SCENE, 10)):
        scene = cell({RL_WORLD_MODEL: 45, SFT: 30, RL_MANISKILL_ONE_SCENE: 35}[method], first=first)
        results["mlp"][method]["scene"] = {"push": scene, "all": scene}
    assert Results.of(results).splits() == ["scene", "ind", "ood"]
    text = format_table({"roboscape_mlp": results["mlp"]}, ["push"], "t", with_paper=True)
    header, _, ours, paper = text.splitlines()[2:6]
    assert header == "| Policy | Training method | Scene Push | IND Push | OOD Push |"
    assert ours.startswith(f"| roboscape_mlp | {RL_WORLD_MODEL} | 90 [")
    # The paper's IND is its initial scene's (section 8.1): beside our scene column; it has no all-scene IND.
    assert paper == f"| *paper: MLP* | *{RL_WORLD_MODEL}* | *98.7* | - | *87.3* |"
    # Its RL w. ManiSkill ran in one scene: beside our run there, none beside our run over every training scene.
    rows = {"roboscape_mlp": results["mlp"] | {RL_MANISKILL: results["mlp"][RL_MANISKILL_ONE_SCENE]}}
    lines = format_table(rows, ["push"], "t", True, paper_methods(rows)).splitlines()
    one_scene = lines.index(next(line for line in lines if f"| {RL_MANISKILL_ONE_SCENE} |" in line))
    assert lines[one_scene + 1] == f"| *paper: MLP* | *{RL_MANISKILL}* | *98.5* | - | *15.6* |"
    assert lines[-1].startswith(f"| roboscape_mlp | {RL_MANISKILL} |")
    targets = claim_targets(results, ["push"])
    assert targets["mlp, Scene Push: PPO in WM, within SFT's interval or above"]["met"]
    assert targets["mlp, IND Push: PPO in WM, within SFT's interval or above"]["met"]
    rows = differences(results, ["push"])
    row = next(r for r in rows if r.key == ("mlp", SFT, "scene", "all"))
    assert row.difference == pytest.approx(0.3)
    # A method evaluated without the scene (a table of the all-scene protocol) leaves the column out.
    del results["mlp"][SFT]["scene"]
    assert Results.of(results).splits() == ["ind", "ood"]
    assert "Scene" not in format_table(results, ["push"], "t")


def test_the_signal_targets_read_the_done_share_and_the_replayed_successes():
    from lerobot_roboscape.experiments.claim_summary import PpoRun
    from lerobot_roboscape.experiments.claim_targets import signal_targets
    from lerobot_roboscape.experiments.replay import Replay

    def run(method, last_success):
        return PpoRun("mlp", method, 40, 360.0, 8600, 0.1, 0.5, 0.0, last_success, 400.0)

    def replay(world_model, simulator):
        return Replay(0, "push", "s0", 1.0, world_model, simulator, "replay_0.mp4")

    replays = [replay(True, True)] * 3 + [replay(True, False)] * 2 + [replay(False, False)] * 11
    targets = signal_targets([run(RL_WORLD_MODEL, 0.25), run(RL_MANISKILL, 0.9)], {RL_WORLD_MODEL: replays})
    fired = targets["mlp: PPO in WM, episodes the done fired in (last iterations)"]
    assert fired["value"] == 0.25 and fired["met"] and len(targets) == 2  # the simulator's run has no done
    confirmed = targets["PPO in WM: its world-model successes that replay as simulator successes"]
    assert confirmed["value"] == 0.6 and confirmed["met"] and confirmed["detail"].startswith("3 of 5")
    silent = signal_targets([run(RL_WORLD_MODEL, 0.0)], {RL_WORLD_MODEL: [replay(False, True)] * 16})
    assert [t["met"] for t in silent.values()] == [False, False]
    assert silent["PPO in WM: its world-model successes that replay as simulator successes"]["value"] is None
    # Each lever's run is read the same way, under its variant's name.
    kl = "RL w. World Model, KL to SFT"
    both = signal_targets([run(RL_WORLD_MODEL, 0.25), run(kl, 0.1)], {RL_WORLD_MODEL: replays, kl: replays[3:]})
    assert not both["mlp: PPO in WM, KL to SFT, episodes the done fired in (last iterations)"]["met"]
    assert both["PPO in WM, KL to SFT: its world-model successes that replay as simulator successes"]["value"] == 0
