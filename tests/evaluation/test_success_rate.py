import dataclasses

import numpy as np
import pytest
import torch
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.policies.factory import make_pre_post_processors
from lerobot_policy_roboscape_mlp import RoboscapeMLPConfig, RoboscapeMLPPolicy

from lerobot_roboscape.evaluation.results import (
    Cell,
    Difference,
    Results,
    difference_interval,
    paired_difference_interval,
    wilson_interval,
)
from lerobot_roboscape.evaluation.success_rate import EvalConfig, eval_env_config, run_episodes
from lerobot_roboscape.rl.policy_loading import PolicyIO
from lerobot_roboscape.tasks import select_scenes
from roboscape_core.errors import InvalidInputError
from tests.rl.reach_env import TARGET, ReachEnv


def test_wilson_interval_known_values():
    assert wilson_interval(0, 10) == pytest.approx((0.0, 0.2775), abs=1e-4)
    assert wilson_interval(10, 10) == pytest.approx((0.7225, 1.0), abs=1e-4)
    assert wilson_interval(5, 10) == pytest.approx((0.2366, 0.7634), abs=1e-4)


def test_difference_interval_matches_newcombe():
    # Newcombe (1998), "Interval estimation for the difference between independent proportions", example (a):
    # 56/70 against 48/80, method 10 (hybrid score): 0.0524 to 0.3339.
    a, b = Cell.of([True] * 56 + [False] * 14), Cell.of([True] * 48 + [False] * 32)
    assert difference_interval(a, b) == pytest.approx((0.2, 0.0524, 0.3339), abs=1e-4)
    d, low, high = difference_interval(b, a)
    assert (d, low, high) == pytest.approx((-0.2, -0.3339, -0.0524), abs=1e-4)  # swapped sides mirror it


# (P(both succeed), P(only a), P(only b)) of a pair of episodes from one initial state
PAIRED_WORLDS = {
    "correlated, a ahead": (0.35, 0.15, 0.05),
    "independent-like": (0.25, 0.25, 0.25),
    "rare": (0.02, 0.06, 0.02),
}


@pytest.mark.parametrize("world", PAIRED_WORLDS)
def test_paired_interval_covers_the_true_difference(world):
    # 2,000 paired experiments of 50 episodes each: the 95% interval holds the true difference in about 95% of them
    # (Newcombe reports his method 10 at or a little above nominal coverage).
    both, only_a, only_b = PAIRED_WORLDS[world]
    rng = np.random.default_rng(0)
    kinds = rng.choice(4, size=(2000, 50), p=[both, only_a, only_b, 1 - both - only_a - only_b])
    covered = 0
    for row in kinds:
        a, b = ((row == 0) | (row == 1)).tolist(), ((row == 0) | (row == 2)).tolist()
        _, low, high = paired_difference_interval(a, b)
        covered += low <= only_a - only_b <= high
    assert 0.93 <= covered / 2000 <= 0.99


def test_paired_interval_is_narrower_when_the_methods_fail_on_the_same_starts():
    # 30 starts both solve, 5 only a, 0 only b, 15 neither: the unpaired interval ignores that the methods agree
    # on 45 of the 50 starts, the paired one uses it.
    a = [True] * 35 + [False] * 15
    b = [True] * 30 + [False] * 20
    d, low, high = paired_difference_interval(a, b)
    _, u_low, u_high = difference_interval(Cell.of(a), Cell.of(b))
    assert d == pytest.approx(0.1)
    assert low > 0 > u_low  # paired: above 0; unpaired: straddles it
    assert high - low < u_high - u_low
    assert paired_difference_interval(b, a) == pytest.approx((-0.1, -high, -low))  # swapped sides mirror it


def test_a_difference_is_paired_only_where_both_cells_kept_their_episodes():
    a, b = [True] * 35 + [False] * 15, [True] * 30 + [False] * 20
    paired = Difference.between(Cell.of(a), Cell.of(b), "mlp", "SFT", "ood", "all")
    _, low, high = paired_difference_interval(a, b)
    assert (
        paired.difference == 0.1 and paired.paired_ci95 == (round(low, 4), round(high, 4)) and paired.kind == "paired"
    )
    unpaired = Difference.between(
        Cell.of(a), dataclasses.replace(Cell.of(b), outcomes=None), "mlp", "SFT", "ood", "all"
    )
    assert unpaired.paired_ci95 is None and unpaired.interval == unpaired.ci95 == paired.ci95


def test_paired_interval_of_identical_outcomes_holds_zero():
    outcomes = [True, False] * 25
    d, low, high = paired_difference_interval(outcomes, outcomes)
    assert d == 0 and low < 0 < high


def test_paired_interval_refuses_unpaired_episodes():
    with pytest.raises(InvalidInputError, match="50 and 49"):
        paired_difference_interval([True] * 50, [True] * 49)


def test_a_cell_keeps_the_episodes_in_order_and_reads_back_as_it_was_written():
    cell = Cell.of([True, False, False, True])
    assert cell.outcomes == (1, 0, 0, 1) and cell.successes == 2 and cell.success_rate == 0.5
    data = cell.to_json()
    assert list(data) == ["success_rate", "successes", "episodes", "ci95", "outcomes"] and data["outcomes"] == [
        1,
        0,
        0,
        1,
    ]
    assert Cell.from_json(data) == cell and "outcomes" not in Cell.from_json(data | {"outcomes": None}).to_json()
    table = {"mlp": {"Supervised finetune": {"ood": {"push": data, "all": data}, "ind": {"push": data, "all": data}}}}
    results = Results.of(table)
    assert results.to_json() == table and results.splits() == ["ind", "ood"]
    assert results.cell("mlp", "Supervised finetune", "ood") == cell and len(list(results.family_cells())) == 2
    with pytest.raises(InvalidInputError, match="no cell for policy 'mlp', method 'RL w. ManiSkill', split 'ood'"):
        results.cell("mlp", "RL w. ManiSkill", "ood")


@pytest.mark.parametrize(("constant_action", "expected"), [(TARGET, True), (-TARGET, False)])
def test_run_episodes_counts_what_the_env_reports(constant_action, expected):
    config = RoboscapeMLPConfig(
        device="cpu",
        input_features={"observation.images.third_view": PolicyFeature(FeatureType.VISUAL, (3, 32, 32))},
        output_features={"action": PolicyFeature(FeatureType.ACTION, (7,))},
        binary_gripper=False,  # the env's target is 0.5 on every dimension, the gripper's included
    )
    policy = RoboscapeMLPPolicy(config)
    with torch.no_grad():  # a policy that always outputs `constant_action`
        policy.action_mean.weight.zero_()
        policy.action_mean.bias.fill_(constant_action)
    stats = {"action": {"min": -torch.ones(7), "max": torch.ones(7)}}
    io = PolicyIO(*make_pre_post_processors(config, dataset_stats=stats))
    success, frames = run_episodes(ReachEnv(32, 3, num_envs=5), policy, io, seed=0, record=True)
    assert success.tolist() == [expected] * 5
    assert len(frames) == 4  # the first frame and one per step


def test_an_evaluation_narrowed_to_a_scene_plays_it_alone():
    initial = select_scenes("ind")[0].id
    env = eval_env_config(EvalConfig(policy_path="x", splits=["ind"], scenes=[initial]), "ind", 64)
    assert [s.id for s in select_scenes(env.split, env.scenes)] == [initial]  # as the env selects its scenes
    held_out = select_scenes("ood")[0].id
    with pytest.raises(InvalidInputError, match=rf"scenes \['{held_out}'\] are not scenes of the splits \['ind'\]"):
        EvalConfig(policy_path="x", splits=["ind"], scenes=[held_out])


def test_unknown_family_is_refused():
    with pytest.raises(ValueError, match="unknown task families"):
        EvalConfig(policy_path="x", families=["juggle"])
