"""Issue 100's audit of PPO where the truth is known: each check that would have caught a PPO that loses SFT's
success in the simulator (a chunk's and a clipped action's log-prob, truncation against termination, a sparse
reward's scaling, the critic's warm-up, the std PPO starts from, train/eval mode), and GRPO's group advantages."""

import math

import numpy as np
import pytest
import torch
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot_policy_roboscape_mlp import RoboscapeMLPConfig, RoboscapeMLPPolicy
from torch.distributions import Normal

from lerobot_roboscape.envs.batched import start_groups
from lerobot_roboscape.rl.policy_loading import PolicyIO, load_policy
from lerobot_roboscape.rl.ppo import train_ppo
from lerobot_roboscape.rl.ppo_losses import group_advantages
from lerobot_roboscape.rl.ppo_state import RunningReturnStats
from lerobot_roboscape.rl.rollout import collect_rollout
from tests.rl.goal_env import GoalEnvConfig
from tests.rl.reach_env import ReachEnvConfig
from tests.rl.test_ppo import logged, mlp_checkpoint, ppo_config


@pytest.fixture
def fresh_mlp(tmp_path):
    return mlp_checkpoint(tmp_path / "sft" / "pretrained_model")


def test_a_chunks_log_prob_sums_its_executed_actions_and_scores_the_unclipped_sample():
    config = RoboscapeMLPConfig(
        device="cpu",
        hidden_dim=16,
        image_feature_dim=8,
        init_log_std=0.5,  # wide: many samples fall outside [-1, 1]
        chunk_size=4,
        n_action_steps=2,
        binary_gripper=True,
        input_features={"observation.images.third_view": PolicyFeature(FeatureType.VISUAL, (3, 16, 16))},
        output_features={"action": PolicyFeature(FeatureType.ACTION, (7,))},
    )
    torch.manual_seed(0)
    policy = RoboscapeMLPPolicy(config).eval()
    batch = {"observation.images.third_view": torch.rand(5, 3, 16, 16), "task": ["pick"] * 5}
    sample = policy.sample_action(batch)
    mean = policy.chunk(policy.features(batch))[:, :2]  # the 2 executed actions of the chunk of 4
    expected = Normal(mean, policy.action_log_std.exp()).log_prob(sample.raw_action).sum((-2, -1))
    torch.testing.assert_close(sample.log_prob, expected)
    assert (sample.raw_action.abs() > 1).any()  # PPO scores the sample itself, as CleanRL ...
    clipped = sample.raw_action.clamp(-1, 1)  # ... the env gets it clipped, the gripper fully open or closed
    torch.testing.assert_close(sample.action[..., :-1], clipped[..., :-1])
    assert set(sample.action[..., -1].unique().tolist()) <= {-1.0, 1.0}
    assert torch.equal(sample.action[..., -1] > 0, clipped[..., -1] >= 0)
    torch.testing.assert_close(policy.evaluate_actions(batch, sample.raw_action).log_prob, sample.log_prob)


def test_the_horizon_truncates_and_bootstraps_from_the_last_observation_success_terminates(fresh_mlp):
    policy, preprocessor, postprocessor = load_policy(fresh_mlp, "cpu")
    io = PolicyIO(preprocessor, postprocessor)
    env = GoalEnvConfig(episode_length=5).create_envs(2)["ppo_test_goal"][0]
    torch.manual_seed(0)
    rollout = collect_rollout(env, policy, io, seed=0)
    assert rollout.truncated[-1].all() and not rollout.terminated.any() and len(rollout.rewards) == 5
    last = io.batch(env._observation()["pixels"], rollout.tasks)  # the frame after the last step, not a reset
    torch.testing.assert_close(rollout.last_value, policy.predict_value(last))
    # With terminate_on_success, an episode at the goal ends terminated: GAE bootstraps nothing after it.
    env = GoalEnvConfig(episode_length=8, terminate_on_success=True, start=0.45).create_envs(2)["ppo_test_goal"][0]
    rollout = collect_rollout(env, policy, io, seed=0)
    assert rollout.terminated[0].all() and not rollout.truncated.any()


def test_a_sparse_rewards_scale_stays_bounded_when_the_first_iterations_pay_nothing():
    stats, alive = RunningReturnStats(), torch.ones(25, 8, dtype=torch.bool)
    for _ in range(10):  # ten iterations without a success
        assert stats.scale_rewards(torch.zeros(25, 8), alive, 0.99).abs().max() == 0
    rewards = torch.zeros(25, 8)
    rewards[10:, 0] = 20.0  # then one episode succeeds and is paid 20 at each step it stays there
    scaled = stats.scale_rewards(rewards, alive, 0.99)
    # Scaled by the spread of the discounted return, this iteration's included: a success is not blown up
    # by the tiny variance of the ten silent iterations.
    assert 0.2 < float(scaled.max()) < 5.0


def test_critic_warmup_trains_the_value_head_and_leaves_the_policy_as_sft_left_it(fresh_mlp, tmp_path):
    from safetensors.torch import load_file

    final = train_ppo(ppo_config(fresh_mlp, tmp_path / "ppo", iterations=3, critic_warmup_iterations=3))
    before, after = load_file(fresh_mlp / "model.safetensors"), load_file(final / "model.safetensors")
    changed = {key for key in before if not torch.equal(before[key], after[key])}
    assert changed and all(key.startswith("value_head.") for key in changed)
    value_loss = logged(tmp_path / "ppo", "losses/value")
    assert value_loss[-1] < value_loss[0]  # the critic catches up before its advantages steer the policy


def test_init_std_sets_the_std_ppo_starts_from_and_a_resume_keeps_the_trained_one(fresh_mlp, tmp_path):
    from safetensors.torch import load_file

    cfg = dict(iterations=2, save_freq=1, init_std=0.05, policy_lr=1e-3, critic_warmup_iterations=0)
    train_ppo(ppo_config(fresh_mlp, tmp_path / "ppo", **cfg))
    first = load_file(tmp_path / "ppo" / "checkpoints" / "00000001" / "pretrained_model" / "model.safetensors")
    # One iteration from log(0.05): 8 Adam steps of lr 1e-3 move each log-std by 0.008 at most.
    np.testing.assert_allclose(first["action_log_std"].numpy(), math.log(0.05), atol=0.009)
    last = train_ppo(ppo_config(fresh_mlp, tmp_path / "ppo", **(cfg | dict(iterations=3, resume=True))))
    resumed = load_file(last / "model.safetensors")["action_log_std"]
    assert not torch.allclose(resumed, torch.full_like(resumed, math.log(0.05)))  # not reset to init_std
    with pytest.raises(ValueError, match="init_std must be > 0"):
        ppo_config(fresh_mlp, tmp_path / "x", init_std=0.0)


def test_the_kl_to_sft_is_to_the_policy_ppo_starts_from_at_its_init_std(fresh_mlp, tmp_path):
    """With init_std, the reference of --kl_coef is SFT at that std too: at the first update (an lr too small to move
    the policy) the KL is 0, not that of two Gaussians of different spreads, which would pull the std back."""
    cfg = dict(iterations=1, init_std=0.05, kl_coef=0.1, policy_lr=1e-9, value_lr=1e-9, critic_warmup_iterations=0)
    train_ppo(ppo_config(fresh_mlp, tmp_path / "ppo", **cfg))
    assert logged(tmp_path / "ppo", "losses/kl_to_reference")[0] == pytest.approx(0.0, abs=1e-4)


def test_rollout_and_update_score_actions_alike_in_eval_and_train_mode(fresh_mlp):
    policy, preprocessor, postprocessor = load_policy(fresh_mlp, "cpu")
    io = PolicyIO(preprocessor, postprocessor)
    env = ReachEnvConfig(episode_length=3).create_envs(4)["ppo_test_reach"][0]
    rollout = collect_rollout(env, policy.eval(), io, seed=0)
    policy.train()  # as PPO's update: its first ratio must be exactly 1
    batch = io.batch({"third_view": rollout.pixels["third_view"][1]}, rollout.tasks)
    torch.testing.assert_close(policy.evaluate_actions(batch, rollout.raw_actions[1]).log_prob, rollout.log_probs[1])


def test_group_advantages_are_success_relative_within_a_group_and_unmixed_groups_are_left_out():
    successes = torch.tensor([1, 0, 0, 0, 1, 1, 1, 1, 0, 1])
    groups = torch.tensor([0, 0, 0, 0, 1, 1, 1, 1, 2, 2])
    advantages, keep = group_advantages(successes, groups, keep_mixed=True)
    std = math.sqrt(0.25 * 0.75)  # group 0: one success of four
    torch.testing.assert_close(advantages[:4], torch.tensor([0.75, -0.25, -0.25, -0.25]) / (std + 1e-6))
    torch.testing.assert_close(advantages[4:8], torch.zeros(4))  # all succeeded: nothing to prefer
    torch.testing.assert_close(advantages[8:], torch.tensor([-0.5, 0.5]) / (0.5 + 1e-6))
    assert keep.tolist() == [True] * 4 + [False] * 4 + [True] * 2
    assert group_advantages(successes, groups, keep_mixed=False)[1].all()


def test_start_groups_are_groups_of_one_family_in_slot_order():
    families = ["pick", "push"] * 4  # dealt in turn, as roboscape_maniskill's slots
    assert start_groups(families, 2).tolist() == [0, 1, 0, 1, 2, 3, 2, 3]
    assert start_groups(families, 1).tolist() == list(range(8))
    with pytest.raises(ValueError, match="group_size=3 does not divide the 4 parallel episodes of task family 'pick'"):
        start_groups(families, 3)


def test_grpo_learns_a_success_that_only_the_success_pays_for(fresh_mlp, tmp_path):
    # Starting near the goal, the random policy sometimes reaches it: groups of 4 from one start have mixed
    # outcomes, and group-relative success alone (no critic, no shaping) is the signal.
    env = GoalEnvConfig(start=0.0, episode_length=4)
    cfg = ppo_config(
        fresh_mlp,
        tmp_path / "grpo",
        env=env,
        num_envs=16,
        iterations=12,
        advantage="group",
        group_size=4,
        policy_lr=1e-2,
    )
    train_ppo(cfg)
    success, kept = logged(tmp_path / "grpo", "charts/success"), logged(tmp_path / "grpo", "charts/groups_kept")
    assert 0 < sum(success[:2]) / 2 < 0.6 and max(kept) >= 1
    assert sum(success[-3:]) / 3 >= sum(success[:2]) / 2 + 0.3
    with pytest.raises(ValueError, match="group_size >= 2 dividing num_envs"):
        ppo_config(fresh_mlp, tmp_path / "x", advantage="group", group_size=3, num_envs=8)
    with pytest.raises(ValueError, match="cannot start episodes in groups"):
        train_ppo(ppo_config(fresh_mlp, tmp_path / "y", advantage="group", group_size=4, iterations=1))
