import pytest
import torch
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.policies.factory import make_pre_post_processors
from lerobot_policy_roboscape_mlp import RoboscapeMLPConfig, RoboscapeMLPPolicy

from lerobot_roboscape.evaluation.success_rate import EvalConfig, difference_interval, run_episodes, wilson_interval
from lerobot_roboscape.rl.policy_loading import PolicyIO
from tests.rl.reach_env import TARGET, ReachEnv


def test_wilson_interval_known_values():
    assert wilson_interval(0, 10) == pytest.approx((0.0, 0.2775), abs=1e-4)
    assert wilson_interval(10, 10) == pytest.approx((0.7225, 1.0), abs=1e-4)
    assert wilson_interval(5, 10) == pytest.approx((0.2366, 0.7634), abs=1e-4)


def test_difference_interval_matches_newcombe():
    # Newcombe (1998), "Interval estimation for the difference between independent proportions", example (a):
    # 56/70 against 48/80, method 10 (hybrid score): 0.0524 to 0.3339.
    a, b = {"successes": 56, "episodes": 70}, {"successes": 48, "episodes": 80}
    assert difference_interval(a, b) == pytest.approx((0.2, 0.0524, 0.3339), abs=1e-4)
    d, low, high = difference_interval(b, a)
    assert (d, low, high) == pytest.approx((-0.2, -0.3339, -0.0524), abs=1e-4)  # swapped sides mirror it


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


def test_unknown_family_is_refused():
    with pytest.raises(ValueError, match="unknown task families"):
        EvalConfig(policy_path="x", families=["juggle"])
