import pytest
import torch
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.policies.factory import get_policy_class, make_pre_post_processors
from lerobot_policy_roboscape_mlp import RoboscapeMLPConfig, RoboscapeMLPPolicy

from tests.conftest import IMAGE_SIZE

CAMERAS = ("observation.images.third_view", "observation.images.wrist")


# One action per look, unaugmented, a continuous gripper: the habits off, unless a test turns one on.
NO_HABITS = dict(random_shift_pad=0, chunk_size=1, n_action_steps=1, binary_gripper=False)


def make_policy(**overrides) -> RoboscapeMLPPolicy:
    features = {key: PolicyFeature(FeatureType.VISUAL, (3, IMAGE_SIZE, IMAGE_SIZE)) for key in CAMERAS}
    features["observation.state"] = PolicyFeature(FeatureType.STATE, (16,))
    config = RoboscapeMLPConfig(
        device="cpu",
        input_features=features,
        hidden_dim=32,
        image_feature_dim=32,
        output_features={"action": PolicyFeature(FeatureType.ACTION, (7,))},
        **(NO_HABITS | overrides),
    )
    torch.manual_seed(0)
    return RoboscapeMLPPolicy(config)


def make_batch(batch_size=4, tasks=None):
    batch = {key: torch.rand(batch_size, 3, IMAGE_SIZE, IMAGE_SIZE) for key in CAMERAS}
    batch["task"] = tasks or ["push the can forward"] * batch_size
    batch["action"] = torch.rand(batch_size, 7) * 2 - 1
    return batch


def test_registered_with_lerobot_and_ignores_state():
    assert get_policy_class("roboscape_mlp") is RoboscapeMLPPolicy
    policy = make_policy()
    assert set(policy.config.input_features) == set(CAMERAS)  # proprioception dropped
    batch = make_batch()  # PPO's critic: the value a sample reports is the value head's
    torch.testing.assert_close(policy.sample_action(batch).value, policy.predict_value(batch))


def test_sft_fits_demonstrations_that_depend_on_image_and_instruction():
    policy = make_policy()
    batch = make_batch(8, ["push the can forward", "pull the mug back"] * 4)
    batch["action"] = torch.tensor([[0.5] * 7, [-0.5] * 7] * 4)  # the instruction alone decides the action
    optimizer = torch.optim.Adam(policy.get_optim_params(), lr=1e-3)
    first = policy.forward(batch)[0].item()
    for _ in range(150):
        loss, _ = policy.forward(batch)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    assert loss.item() < 0.01 * first
    assert torch.allclose(policy.select_action(batch), batch["action"], atol=0.1)


@pytest.mark.parametrize(("chunk_size", "n_action_steps"), [(1, 1), (4, 3)])
def test_sampled_log_probs_match_evaluation_and_the_gaussian(chunk_size, n_action_steps):
    # PPO samples the actions evaluation executes per look: the chunk's first n_action_steps, scored together.
    policy = make_policy(init_log_std=-1.0, chunk_size=chunk_size, n_action_steps=n_action_steps)
    batch = make_batch()
    sample = policy.sample_action(batch)
    assert sample.action.shape == (4, n_action_steps, 7)
    assert sample.log_prob.shape == (4,) and sample.value.shape == (4,)
    evaluation = policy.evaluate_actions(batch, sample.raw_action)
    torch.testing.assert_close(evaluation.log_prob, sample.log_prob)
    torch.testing.assert_close(evaluation.value, sample.value)
    with torch.no_grad():
        mean = policy.chunk(policy.features(batch))[:, :n_action_steps]
    expected = torch.distributions.Normal(mean, torch.full_like(mean, torch.e**-1.0)).log_prob(sample.raw_action)
    torch.testing.assert_close(sample.log_prob, expected.sum((-2, -1)))
    std_entropy = 0.5 * (1 + torch.log(torch.tensor(2 * torch.pi))) - 1.0  # of N(., e^-1) per dimension
    torch.testing.assert_close(evaluation.entropy, torch.full((4,), n_action_steps * 7 * std_entropy.item()))


def test_save_and_load_round_trip(tmp_path):
    policy = make_policy()
    batch = make_batch()
    policy.save_pretrained(tmp_path)
    loaded = RoboscapeMLPPolicy.from_pretrained(tmp_path)
    torch.testing.assert_close(loaded.select_action(batch), policy.select_action(batch))


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda b: b.pop("observation.images.wrist"), "expects camera 'observation.images.wrist'"),
        (lambda b: b.update({"observation.images.wrist": torch.rand(4, 3, 16, 16)}), r"\(3, 16, 16\)"),
        (lambda b: b.pop("task"), "instruction"),
    ],
)
def test_bad_input_names_what_is_wrong(change, message):
    batch = make_batch()
    change(batch)
    with pytest.raises((KeyError, ValueError), match=message):
        make_policy().select_action(batch)


def test_lerobot_train_checkpoint_has_processors_with_action_statistics(mlp_checkpoint):
    assert (mlp_checkpoint / "policy_preprocessor.json").exists()
    run_dir = mlp_checkpoint.parents[2]
    assert list((run_dir / "eval").glob("videos_step_000004/roboscape_maniskill_0/*.mp4"))  # periodic evaluation
    policy = RoboscapeMLPPolicy.from_pretrained(mlp_checkpoint)
    preprocessor, postprocessor = make_pre_post_processors(policy.config, pretrained_path=str(mlp_checkpoint))
    observation = {key: torch.rand(3, IMAGE_SIZE, IMAGE_SIZE) for key in CAMERAS}
    batch = preprocessor({**observation, "task": "push the can forward"})
    action = postprocessor(policy.select_action(batch))
    assert action.shape == (1, 7) and torch.isfinite(action).all()


def test_random_shift_translates_each_image_within_its_padding():
    from lerobot_policy_roboscape_mlp.modeling_roboscape_mlp import random_shift

    images = torch.zeros(16, 3, 12, 12)
    images[:, :, 6, 6] = 1.0  # one bright pixel
    shifted = random_shift(images, pad=2)
    assert shifted.shape == images.shape
    ys, xs = [], []
    for image in shifted:
        y, x = (image[0] == 1).nonzero()[0].tolist()
        ys.append(y)
        xs.append(x)
    assert all(4 <= v <= 8 for v in ys + xs)  # moved by at most the padding
    assert len(set(zip(ys, xs, strict=True))) > 1  # and not all alike


def test_chunk_loss_ignores_the_steps_past_the_episode_end():
    policy = make_policy(chunk_size=3)
    batch = make_batch()
    chunk = policy.predict_action_chunk(batch)
    assert chunk.shape == (4, 3, 7)
    batch["action"] = chunk.clone()
    batch["action"][:, 2] = 5.0  # far off, but padding
    batch["action_is_pad"] = torch.tensor([[False, False, True]] * 4)
    loss, info = policy.forward(batch)
    assert loss.item() < 1e-10 and info["mse_first"] < 1e-10
    batch["action_is_pad"][:, 2] = False
    assert policy.forward(batch)[0].item() > 1.0


def test_executing_a_chunk_asks_the_network_once_per_n_action_steps():
    policy = make_policy(chunk_size=4, n_action_steps=3)
    batch = make_batch()
    chunk = policy.predict_action_chunk(batch)
    calls = []
    policy.trunk.register_forward_hook(lambda *_: calls.append(1))
    policy.reset()
    actions = [policy.select_action(batch) for _ in range(4)]
    assert len(calls) == 2  # steps 0 and 3
    for t in range(3):
        torch.testing.assert_close(actions[t], chunk[:, t])
    torch.testing.assert_close(actions[3], chunk[:, 0])  # same images, so the new chunk starts alike


def test_binary_gripper_is_fully_open_or_closed_and_ppo_scores_the_raw_sample():
    policy = make_policy(binary_gripper=True, init_log_std=0.0, chunk_size=2)
    batch = make_batch(64)
    assert set(policy.select_action(batch)[:, -1].tolist()) <= {-1.0, 1.0}
    sample = policy.sample_action(batch)
    assert set(sample.action[..., -1].flatten().tolist()) == {-1.0, 1.0}
    assert not set(sample.raw_action[..., -1].flatten().tolist()) <= {-1.0, 1.0}
    # PPO's Gaussian is over the chunk's executed action (n_action_steps=1 here), and evaluation scores the same
    # sample alike.
    torch.testing.assert_close(
        policy.distribution(policy.features(batch)).mean, policy.chunk(policy.features(batch))[:, :1]
    )
    torch.testing.assert_close(policy.evaluate_actions(batch, sample.raw_action).log_prob, sample.log_prob)


def test_tokenizer_encoder_trunk_is_the_frozen_tokenizer_encoder(trained_tokenizer, tmp_path):
    from lerobot_roboscape.tokenizer.modeling_tokenizer import VisualTokenizer, encoder_input

    policy = make_policy(tokenizer_path=str(trained_tokenizer))
    tokenizer = VisualTokenizer.from_pretrained(trained_tokenizer)
    encoder = policy.image_encoder.encoder
    assert not any(p.requires_grad for p in encoder.parameters())
    images = torch.rand(2, 3, IMAGE_SIZE, IMAGE_SIZE)
    torch.testing.assert_close(encoder(encoder_input(images)), tokenizer.encoder(encoder_input(images)))
    # SFT trains the head, not the encoder.
    batch = make_batch()
    before = {k: v.clone() for k, v in encoder.state_dict().items()}
    policy.train()
    policy.forward(batch)[0].backward()
    torch.optim.SGD([p for p in policy.parameters() if p.requires_grad], lr=0.1).step()
    assert all(torch.equal(before[k], v) for k, v in encoder.state_dict().items())
    policy.eval()
    policy.save_pretrained(tmp_path)
    torch.testing.assert_close(
        RoboscapeMLPPolicy.from_pretrained(tmp_path).select_action(batch), policy.select_action(batch)
    )
