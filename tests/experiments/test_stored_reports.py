"""The committed results re-render byte for byte from their JSON: each stored Table 1, and the paper protocol's
claim report with its targets and differences (the command it gives, parsed back, is its config). A change to the
results' types or to the report's code that changes a stored report shows here."""

import json
import re
import shlex
from pathlib import Path

import pytest

from lerobot_roboscape.envs.reward_readings import RewardReadings
from lerobot_roboscape.evaluation.tables import format_table
from lerobot_roboscape.experiments.claim_markdown import markdown
from lerobot_roboscape.experiments.claim_summary import ClaimSummary
from lerobot_roboscape.experiments.claim_targets import claim_targets
from lerobot_roboscape.experiments.experiment import ExperimentConfig
from lerobot_roboscape.experiments.experiment_report import differences
from lerobot_roboscape.pipeline.config import parse_config
from lerobot_roboscape.pipeline.report.world_model_targets import done_targets, goal_targets
from lerobot_roboscape.reward.done_readings import DoneReport

RESULTS = Path(__file__).parents[2] / "docs" / "results"


@pytest.mark.parametrize("name", ["bench", "claim", "claim_paper"])
def test_each_stored_table_1_renders_again_from_its_json(name):
    summary = json.loads((RESULTS / name / "results.json").read_text())
    table = format_table(summary["table"], summary["families"], f"{summary['scale']} scale")
    assert table == (RESULTS / name / "tables.md").read_text()


def test_the_claim_report_renders_again_from_its_json():
    folder = RESULTS / "claim_paper"
    text, summary = (folder / "report.md").read_text(), json.loads((folder / "results.json").read_text())
    command = re.search(r"`(roboscape-experiment [^`]*)`", text).group(1)
    cfg = parse_config(ExperimentConfig, shlex.split(command)[1:], "pipeline.")
    assert claim_targets(summary["table"], summary["families"], summary["curve"]) == summary["targets"]
    assert [d.to_json() for d in differences(summary["table"], summary["families"])] == summary["differences"]
    assert markdown(cfg, summary) == text
    assert ClaimSummary.from_json(summary).to_json() == summary  # read and written back, field for field


def test_the_world_models_done_and_goal_targets_render_again_from_their_stored_reports():
    stored = json.loads((RESULTS / "world_model" / "results.json").read_text())
    for results in (stored, stored["bench_on_gpu"]):
        done = DoneReport.from_json(results["done"])
        assert done.choice() == results["done"]["chosen"]
        targets = done_targets(done)
        assert targets == {name: t for name, t in results["targets"].items() if name.startswith("done")}
        readings = {"summary": results["reward"], "goals": results["goals"], "similarity": results["similarity"]}
        targets = goal_targets(RewardReadings.from_json(readings | {"done_source": "world_model", "theta": 0.5}))
        assert targets == {name: t for name, t in results["targets"].items() if name.startswith("goal")}


def test_the_claim_report_says_how_many_episodes_a_guard_without_an_ensemble_halted():
    folder = RESULTS / "claim72_gpuwm"
    text, summary = (folder / "report.md").read_text(), json.loads((folder / "results.json").read_text())
    command = re.search(r"`(roboscape-experiment [^`]*)`", text).group(1)
    cfg = parse_config(ExperimentConfig, shlex.split(command)[1:], "pipeline.")
    assert markdown(cfg, summary) == text
    plain = next(run for run in summary["ppo_runs"] if run["method"] == "RL w. World Model")
    plain["last_halted"] = 0.25  # as the range lever's run reports it
    assert (
        "Episodes of RL w. World Model halted where the predicted robot state left the data's range: 25% over its "
        "last 3 iterations." in markdown(cfg, summary)
    )
