import json
from dataclasses import replace

import numpy as np
import pytest
import torch
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.policies.factory import make_pre_post_processors
from lerobot_policy_roboscape_mlp import RoboscapeMLPConfig, RoboscapeMLPPolicy
from safetensors.torch import load_file

from lerobot_roboscape.envs.configs import RoboscapeManiSkillEnvConfig
from lerobot_roboscape.rl.configuration_ppo import PPOConfig
from lerobot_roboscape.rl.history import read_ppo_history
from lerobot_roboscape.rl.policy_loading import PolicyIO, load_policy
from lerobot_roboscape.rl.ppo import train_ppo
from lerobot_roboscape.rl.ppo_losses import compute_gae, kl_to_reference, ppo_losses
from lerobot_roboscape.rl.rollout import collect_rollout
from lerobot_roboscape.training.checkpoints import CHECKPOINTS, FINAL, LOGS, PPO_CONFIG_JSON, last_checkpoint
from tests.rl.goal_env import GoalEnvConfig
from tests.rl.reach_env import ReachEnvConfig


def test_gae_against_a_hand_computed_case():
    # Three envs, three steps. Env 0 terminates at step 1 (its step 2 is after the end); env 1 runs to the time
    # limit and bootstraps from the last value; env 2 reaches its (shorter) horizon at step 1 and bootstraps from
    # the value of the observation after it, values[2].
    rewards = torch.tensor([[1.0, 0.0, 1.0], [2.0, 1.0, 1.0], [0.0, 1.0, 5.0]])
    values = torch.tensor([[0.5, 0.2, 1.0], [1.0, 0.4, 2.0], [9.0, 0.6, 3.0]])
    terminated = torch.tensor([[False, False, False], [True, False, False], [False, False, False]])
    truncated = torch.tensor([[False, False, False], [False, False, True], [False, False, False]])
    last_value = torch.tensor([7.0, 0.8, 4.0])
    gamma, lam = 0.9, 0.8
    advantages, returns = compute_gae(rewards, values, terminated, truncated, last_value, gamma, lam)
    # env 0: delta1 = 2 - 1 = 1 (terminal: no bootstrap); delta0 = 1 + 0.9*1.0 - 0.5 = 1.4
    #        A1 = 1, A0 = 1.4 + 0.9*0.8*1 = 2.12
    # env 1: delta2 = 1 + 0.9*0.8 - 0.6 = 1.12; delta1 = 1 + 0.9*0.6 - 0.4 = 1.14; delta0 = 0 + 0.9*0.4 - 0.2 = 0.16
    #        A2 = 1.12, A1 = 1.14 + 0.72*1.12 = 1.9464, A0 = 0.16 + 0.72*1.9464 = 1.561408
    torch.testing.assert_close(advantages[:2, 0], torch.tensor([2.12, 1.0]))
    torch.testing.assert_close(advantages[:, 1], torch.tensor([1.561408, 1.9464, 1.12]))
    # env 2: delta1 = 1 + 0.9*3 - 2 = 1.7 (truncated: bootstrap, and the recursion stops: step 2 is after the end)
    #        delta0 = 1 + 0.9*2 - 1 = 1.8; A0 = 1.8 + 0.72*1.7 = 3.024
    torch.testing.assert_close(advantages[:2, 2], torch.tensor([3.024, 1.7]))
    torch.testing.assert_close(returns, advantages + values)


def test_ppo_loss_terms_on_known_inputs():
    old = torch.zeros(3)
    new = torch.log(torch.tensor([1.5, 0.5, 1.1]))  # ratios 1.5, 0.5, 1.1
    advantages = torch.tensor([1.0, 1.0, -2.0])
    losses = ppo_losses(
        new,
        old,
        advantages,
        new_value=torch.tensor([1.0, 0.0, 3.0]),
        old_value=torch.tensor([0.0, 0.0, 0.0]),
        returns=torch.tensor([1.0, 1.0, 1.0]),
        entropy=torch.tensor([0.3, 0.3, 0.3]),
        clip_coef=0.2,
        value_clip_coef=0.5,
        value_loss="mse",
    )
    # -min(r*A, clip(r)*A): 1.5 -> -1.2; 0.5 -> -0.5 (unclipped side is smaller); 1.1 with A=-2 -> 2.2
    torch.testing.assert_close(losses.policy, torch.tensor((-1.2 - 0.5 + 2.2) / 3))
    # value: max(0.5*(v-R)^2, 0.5*(clipped-R)^2) with clipped = 0.5, 0, 0.5 -> max(0, .125), max(.5, .5), max(2, .125)
    torch.testing.assert_close(losses.value, torch.tensor((0.125 + 0.5 + 2.0) / 3))
    torch.testing.assert_close(losses.clip_fraction, torch.tensor(2 / 3))
    torch.testing.assert_close(losses.entropy, torch.tensor(0.3))
    huber = ppo_losses(
        new,
        old,
        advantages,
        torch.tensor([4.0]),
        torch.tensor([4.0]),
        torch.tensor([1.0]),
        torch.zeros(1),
        0.2,
        None,
        value_loss="huber",
        huber_delta=1.0,
    )
    torch.testing.assert_close(huber.value, torch.tensor(3.0 - 0.5))  # linear beyond delta: delta*(|e| - delta/2)


def mlp_checkpoint(path, chunk_size: int = 1, n_action_steps: int = 1):
    """A randomly initialised roboscape_mlp checkpoint (with processors) for 32 px third-view images."""
    config = RoboscapeMLPConfig(
        device="cpu",
        hidden_dim=32,
        image_feature_dim=16,
        init_log_std=-1.0,
        # The plain head: these tests check PPO, whose envs want 0.5 on every dimension, the gripper's included.
        chunk_size=chunk_size,
        n_action_steps=n_action_steps,
        binary_gripper=False,
        input_features={"observation.images.third_view": PolicyFeature(FeatureType.VISUAL, (3, 32, 32))},
        output_features={"action": PolicyFeature(FeatureType.ACTION, (7,))},
    )
    torch.manual_seed(0)
    policy = RoboscapeMLPPolicy(config)
    stats = {"action": {"min": -torch.ones(7), "max": torch.ones(7)}}
    policy.save_pretrained(path)
    for processor in make_pre_post_processors(config, dataset_stats=stats):
        processor.save_pretrained(path)
    return path


@pytest.fixture
def fresh_mlp(tmp_path):
    return mlp_checkpoint(tmp_path / "sft" / "pretrained_model")


@pytest.fixture
def chunked_mlp(tmp_path):
    """Predicts 4 actions per look and executes 2 of them, as `n_action_steps` makes evaluation do."""
    return mlp_checkpoint(tmp_path / "chunked" / "pretrained_model", chunk_size=4, n_action_steps=2)


def ppo_config(policy_path, output_dir, **overrides) -> PPOConfig:
    kwargs = dict(
        policy_path=str(policy_path),
        env=ReachEnvConfig(),
        output_dir=output_dir,
        num_envs=8,
        iterations=12,
        policy_lr=3e-3,
        value_lr=3e-3,
        minibatch_size=16,
        device="cpu",
        mixed_precision="no",
        save_freq=4,
    )
    return PPOConfig(**{**kwargs, **overrides})


def saved_state(final, name: str) -> dict:
    """What the run of the model `final` saved beside its newest checkpoint (its training_state/<name>.json)."""
    return json.loads((last_checkpoint(final.parent) / "training_state" / f"{name}.json").read_text())


def logged(output_dir, tag: str = "charts/episode_return") -> list[float]:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(next(output_dir.glob(f"{LOGS}/events*")).parent))
    events.Reload()
    return [event.value for event in events.Scalars(tag)]


def test_kl_to_reference_estimates_the_kl_of_two_gaussians():
    policy = torch.distributions.Normal(0.0, 1.0)
    reference = torch.distributions.Normal(0.5, 1.2)
    torch.manual_seed(0)
    samples = policy.sample((200_000,))
    exact = torch.distributions.kl_divergence(policy, reference)
    estimate = kl_to_reference(policy.log_prob(samples), reference.log_prob(samples))
    assert abs(float(estimate - exact)) < 0.01 * float(exact) + 2e-3
    assert kl_to_reference(policy.log_prob(samples), policy.log_prob(samples)) == 0


def test_kl_penalty_keeps_the_policy_near_the_one_ppo_started_from(fresh_mlp, tmp_path):
    kwargs = dict(iterations=4, critic_warmup_iterations=0)
    train_ppo(ppo_config(fresh_mlp, tmp_path / "free", kl_coef=1e-9, **kwargs))  # measured, not penalised
    train_ppo(ppo_config(fresh_mlp, tmp_path / "held", kl_coef=30.0, **kwargs))
    free, held = (logged(tmp_path / run, "losses/kl_to_reference") for run in ("free", "held"))
    assert min(free + held) >= 0
    assert max(held) < max(free) / 3 and held[-1] < free[-1] / 10


def test_ppo_improves_the_return_on_a_certain_task(fresh_mlp, tmp_path):
    final = train_ppo(ppo_config(fresh_mlp, tmp_path / "ppo", iterations=15, video_freq=10))
    returns = logged(tmp_path / "ppo")
    assert len(returns) == 15
    assert sum(returns[-3:]) / 3 > sum(returns[:3]) / 3 + 0.5  # out of a maximum of 4
    assert (final / "policy_postprocessor.json").exists() and (final / "model.safetensors").exists()
    assert list((tmp_path / "ppo" / "videos").glob("*.mp4"))


def test_a_chunked_policy_decides_every_k_steps_and_is_paid_their_summed_reward(chunked_mlp):
    policy, preprocessor, postprocessor = load_policy(chunked_mlp, "cpu")
    env = ReachEnvConfig(episode_length=5).create_envs(3)["ppo_test_reach"][0]
    torch.manual_seed(0)
    rollout = collect_rollout(env, policy, PolicyIO(preprocessor, postprocessor), seed=0)
    assert env.t == 5  # 2 + 2 + 1 env steps: the last chunk is cut where the horizon ends the episode
    assert rollout.raw_actions.shape == (3, 3, 2, 7)  # (decisions, envs, executed actions, action_dim)
    executed = rollout.raw_actions.clamp(-1, 1)  # the env's actions (the processors' range is [-1, 1])
    paid = 1 - (executed - 0.5).abs().mean(-1)  # (decisions, envs, k) each step's reach reward
    torch.testing.assert_close(rollout.rewards[:2], paid[:2].sum(-1))
    torch.testing.assert_close(rollout.rewards[2], paid[2, :, 0])
    assert rollout.truncated[2].all() and not rollout.truncated[:2].any()
    evaluation = policy.evaluate_actions(
        PolicyIO(preprocessor, postprocessor).batch({"third_view": rollout.pixels["third_view"][0]}, rollout.tasks),
        rollout.raw_actions[0],
    )
    torch.testing.assert_close(evaluation.log_prob, rollout.log_probs[0])  # the k actions scored as one choice


def test_an_ensembles_disagreement_and_halts_are_summed_over_the_running_steps(fresh_mlp):
    """An env that reports an ensemble's disagreement (roboscape_wm with one) has it summed per episode over the
    steps each episode ran, and its halts counted; an env that reports none has neither."""
    policy, preprocessor, postprocessor = load_policy(fresh_mlp, "cpu")
    io = PolicyIO(preprocessor, postprocessor)
    env = ReachEnvConfig(episode_length=4).create_envs(2)["ppo_test_reach"][0]
    assert collect_rollout(env, policy, io, seed=0).disagreement is None
    plain_step = env.step

    def step(actions):  # episode 0 halted at its second step; each running step reports 0.25 nats for episode 1
        observation, reward, terminated, truncated, info = plain_step(actions)
        halted = np.array([env.t >= 2, False])
        terminated = terminated | halted
        return observation, reward, terminated, truncated, info | {"disagreement": np.full(2, 0.25), "halted": halted}

    env.step = step
    rollout = collect_rollout(env, policy, io, seed=0)
    np.testing.assert_allclose(rollout.disagreement, [0.5, 1.0])  # 2 running steps, then 4
    assert rollout.halted.tolist() == [True, False]


def test_target_kl_stops_the_update_once_the_policy_moved_that_far(fresh_mlp, tmp_path):
    kwargs = dict(iterations=3, critic_warmup_iterations=0)
    train_ppo(ppo_config(fresh_mlp, tmp_path / "free", **kwargs))
    train_ppo(ppo_config(fresh_mlp, tmp_path / "held", target_kl=1e-9, **kwargs))
    assert logged(tmp_path / "free", "charts/update_stopped_by_kl") == [0.0] * 3
    # The first minibatch scores the rollout's own policy (KL 0) and steps; the next one finds it moved.
    assert logged(tmp_path / "held", "charts/update_stopped_by_kl") == [1.0] * 3
    assert max(logged(tmp_path / "held", "losses/approx_kl")) < max(logged(tmp_path / "free", "losses/approx_kl"))


def test_ppo_on_chunks_improves_the_return(chunked_mlp, tmp_path):
    # Half the decisions of a one-action policy per episode: as many samples per iteration with twice the envs.
    train_ppo(ppo_config(chunked_mlp, tmp_path / "ppo", num_envs=16, iterations=25))
    returns = logged(tmp_path / "ppo")
    assert sum(returns[-3:]) / 3 > sum(returns[:3]) / 3 + 0.5  # out of a maximum of 4


@pytest.mark.parametrize("terminate_on_success", [False, True])
def test_ppo_learns_success_that_the_shaping_reward_alone_does_not_pay_for(fresh_mlp, tmp_path, terminate_on_success):
    # The shaping reward is positive at every step, success comes only from reaching the goal. Had success ended
    # the episode without a bonus, it would be worth less than wandering, and the success rate would not rise.
    env = GoalEnvConfig(terminate_on_success=terminate_on_success)
    train_ppo(ppo_config(fresh_mlp, tmp_path / "ppo", env=env, iterations=10, critic_warmup_iterations=1))
    success = logged(tmp_path / "ppo", "charts/success")
    assert success[0] == 0.0  # a poor start: the random policy never reaches the goal
    assert sum(success[-3:]) / 3 >= 0.5


def test_resume_equals_uninterrupted_training(fresh_mlp, tmp_path):
    reference = train_ppo(ppo_config(fresh_mlp, tmp_path / "reference", iterations=6, save_freq=2))
    train_ppo(ppo_config(fresh_mlp, tmp_path / "interrupted", iterations=4, save_freq=2))  # "killed" after 4
    resumed = train_ppo(ppo_config(fresh_mlp, tmp_path / "interrupted", iterations=6, save_freq=2, resume=True))
    assert saved_state(resumed, "iteration")["iteration"] == 6
    expected, got = load_file(reference / "model.safetensors"), load_file(resumed / "model.safetensors")
    assert expected.keys() == got.keys()
    assert all(torch.equal(expected[key], got[key]) for key in expected)
    with pytest.raises(FileExistsError, match="--resume=true"):
        train_ppo(ppo_config(fresh_mlp, tmp_path / "interrupted", iterations=8))


def test_time_budget_stops_the_run_and_history_records_each_iteration(fresh_mlp, tmp_path):
    final = train_ppo(ppo_config(fresh_mlp, tmp_path / "ppo", iterations=12, time_budget_s=1e-6))
    state = saved_state(final, "iteration")
    clock = saved_state(final, "clock")
    assert state["iteration"] == 1 and clock["seconds"] > 0  # the first iteration spends the budget; it is saved
    history = read_ppo_history(tmp_path / "ppo")
    assert [row.iteration for row in history] == [1] and history[0].seconds == clock["seconds"]
    assert history[0].samples > 0 and 0 <= history[0].success <= 1 and history[0].disagreement is None


def test_a_finished_run_given_a_larger_time_budget_goes_on_from_where_it_stopped(fresh_mlp, tmp_path):
    from lerobot_roboscape.pipeline.ppo_run import ppo

    cfg = ppo_config(fresh_mlp, tmp_path / "ppo", iterations=12, time_budget_s=1e-6)
    first = ppo(cfg)
    clock = saved_state(first, "clock")["seconds"]
    # The budget grows past the first iteration's clock: the second iteration spends it, on top of the first.
    longer = ppo(replace(cfg, time_budget_s=clock + 1e-6))
    assert saved_state(longer, "iteration")["iteration"] == 2
    assert [row.iteration for row in read_ppo_history(tmp_path / "ppo")] == [1, 2]
    assert read_ppo_history(tmp_path / "ppo")[1].seconds > clock  # PPO's clock went on from the first run's
    saved = [tmp_path / "ppo" / CHECKPOINTS / step / FINAL / "model.safetensors" for step in ("00000001", "00000002")]
    assert (longer / "model.safetensors").read_bytes() == saved[1].read_bytes() != saved[0].read_bytes()  # republished
    # with the flags it trained under beside it, as beside a checkpoint's (the Hub card reads them there)
    assert (longer.parent / PPO_CONFIG_JSON).read_text() == (saved[1].parent.parent / PPO_CONFIG_JSON).read_text()
    shorter = ppo(replace(cfg, time_budget_s=1e-7))  # a smaller budget is another run: it starts again
    assert saved_state(shorter, "iteration")["iteration"] == 1


def test_bad_checkpoint_path_and_env_mismatch_are_clear_errors(fresh_mlp, tmp_path):
    with pytest.raises(FileNotFoundError, match="No LeRobot policy checkpoint at .*missing"):
        train_ppo(ppo_config(tmp_path / "missing", tmp_path / "a"))
    with pytest.raises(ValueError, match="--env.image_size=32"):
        train_ppo(ppo_config(fresh_mlp, tmp_path / "b", env=ReachEnvConfig(image_size=16)))
    with pytest.raises(ValueError, match="observation.images.third_view"):
        config = RoboscapeManiSkillEnvConfig(image_size=32, cameras=("wrist",))
        train_ppo(ppo_config(fresh_mlp, tmp_path / "c", env=config))


def test_unknown_policy_type_needs_every_setting(fresh_mlp, tmp_path):
    with pytest.raises(ValueError, match="no defaults for policy type 'act'.*--update_epochs"):
        ppo_config(fresh_mlp, tmp_path / "ppo").with_policy_defaults("act")
    explicit = dict(
        policy_lr=1e-4,
        value_lr=1e-3,
        update_epochs=1,
        minibatch_size=4,
        grad_accum_steps=1,
        max_grad_norm=1.0,
        value_loss="huber",
        vf_coef=1.0,
        critic_warmup_iterations=0,
    )
    assert ppo_config(fresh_mlp, tmp_path / "ppo", **explicit).with_policy_defaults("act").value_loss == "huber"
    with pytest.raises(ValueError, match="value_loss must be mse or huber"):
        ppo_config(fresh_mlp, tmp_path / "ppo", value_loss="l1")


def test_a_policy_must_execute_a_world_model_frame_of_actions():
    """The world model makes a frame every k actions: a policy that executes chunks must execute k of them per look
    (the MLP's 4 at k = 4), one that acts every step (OpenVLA) always fits; any other chunk is refused by name."""
    from types import SimpleNamespace

    from lerobot_roboscape.rl.policy_loading import check_policy_fits_frame_skip
    from roboscape_core.errors import InvalidInputError

    env = SimpleNamespace(frame_skip=4)
    for executed in (1, 4):
        check_policy_fits_frame_skip(SimpleNamespace(config=SimpleNamespace(n_action_steps=executed)), env, "p")
    with pytest.raises(InvalidInputError, match=r"executes 8 actions per look.*every 4 actions.*n_action_steps=4"):
        check_policy_fits_frame_skip(SimpleNamespace(config=SimpleNamespace(n_action_steps=8)), env, "p")
