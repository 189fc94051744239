"""The world model's architecture: its presets, shapes and causality, its control path (AdaLN, normalisation, dropout,
guidance), its patches and state, its checkpoints, and the errors it names."""

import pytest
import torch

from lerobot_roboscape.robot import STATE_DIM, TCP_QUATERNION
from lerobot_roboscape.world_model.configuration_world_model import PaperWorldModelConfig, TinyWorldModelConfig
from lerobot_roboscape.world_model.control_encoders import ACTION_STD_FLOOR
from lerobot_roboscape.world_model.modeling_world_model import STWorldModel
from lerobot_roboscape.world_model.rollout import Rollout
from roboscape_core.errors import InvalidInputError
from tests.world_model.micro import (
    CONTROL_PATH,
    MICRO,
    STATS,
    TASKS,
    VARIANTS,
    control_kwargs,
    make_model,
    random_batch,
)

# The control path's levers together, each active (the AdaLN projections and the null text token start at 0).


def test_paper_preset_matches_the_paper():
    cfg = PaperWorldModelConfig()
    assert (
        cfg.n_layer,
        cfg.n_head,
        cfg.d_model,
        cfg.tokens_per_side,
        cfg.window,
        cfg.prompt_frames,
        cfg.maskgit_steps,
    ) == (32, 8, 512, 16, 16, 8, 2)


@pytest.mark.parametrize("control", ["action", "text"])
def test_shapes_and_loss(control):
    model = make_model(control)
    batch = random_batch()
    control_tokens = model.encode_control(batch["actions"], batch["no_action"], batch["task"])
    logits, done, kvs = model.compute_logits(batch["tokens"], control_tokens, states=batch["state"])
    assert logits.shape == (2, 4, 8, 16) and done.shape == (2, 4)
    assert len(kvs) == 2 and kvs[0][0].shape == (2 * 8, 2, 4, 16)  # (B * S, heads, T, head_dim)
    loss, logs = model.train()(batch)
    loss.backward()
    assert torch.isfinite(loss) and set(logs) >= {"token_ce", "token_acc", "done_loss", "state_mse"}


@pytest.mark.parametrize("control,overrides", VARIANTS)
def test_future_frames_never_influence_the_past(control, overrides):
    model = make_model(control, **overrides)
    batch = random_batch()
    control_tokens = model.encode_control(batch["actions"], batch["no_action"], batch["task"])
    logits, done, _ = model.compute_logits(batch["tokens"], control_tokens, states=batch["state"])
    changed = batch["tokens"].clone()
    changed[:, 2:] = (changed[:, 2:] + 5) % 16
    states = batch["state"].clone()
    states[:, 2:] += 1.0
    if control == "action":
        batch["actions"][:, 2:] = -batch["actions"][:, 2:]
        control_tokens = model.encode_control(batch["actions"], batch["no_action"])
    logits2, done2, _ = model.compute_logits(changed, control_tokens, states=states)
    torch.testing.assert_close(logits2[:, :2], logits[:, :2])
    torch.testing.assert_close(done2[:, :2], done[:, :2])
    assert not torch.allclose(logits2[:, 2:], logits[:, 2:])


def test_adaln_starts_from_its_block_and_then_reaches_every_token_of_its_frame():
    batch = random_batch()
    plain = make_model(adaln="none")
    torch.manual_seed(0)  # unperturbed: the zero-initialised modulation, as training starts
    fresh = STWorldModel(TinyWorldModelConfig(control="action", adaln="one_plus", **MICRO, **STATS)).eval()
    states = batch["state"]
    control = fresh.encode_control(batch["actions"], batch["no_action"])
    logits = fresh.compute_logits(batch["tokens"], control, states=states)[0]
    # the same weights as the model without AdaLN: the same function
    plain.load_state_dict({k: v for k, v in fresh.state_dict().items() if "modulation" not in k})
    control = plain.encode_control(batch["actions"], batch["no_action"])
    expected = plain.compute_logits(batch["tokens"], control, states=states)
    torch.testing.assert_close(logits, expected[0])

    model = make_model(adaln="one_plus")
    for block in model.blocks:  # no cross-attention path: what remains is the modulation
        torch.nn.init.zeros_(block.cross.proj.weight)
        torch.nn.init.zeros_(block.cross.proj.bias)
    flipped = batch["actions"].clone()
    flipped[:, 2] = -flipped[:, 2]  # frame 2's action only
    states = batch["state"]
    a = model.compute_logits(
        batch["tokens"], model.encode_control(batch["actions"], batch["no_action"]), states=states
    )[0]
    b = model.compute_logits(batch["tokens"], model.encode_control(flipped, batch["no_action"]), states=states)[0]
    torch.testing.assert_close(a[:, :2], b[:, :2])
    assert ((a[:, 2] - b[:, 2]).abs().amax(-1) > 1e-6).all()  # every token of frame 2


def test_actions_are_normalised_by_the_dataset_statistics():
    normalised = make_model()
    raw = make_model(action_mean=None, action_std=None)
    raw.load_state_dict(normalised.state_dict())
    actions = torch.rand(2, 3, 1, 7) * 0.7 - 0.35
    std = torch.tensor(STATS["action_std"])
    expected = raw.encode_control((actions - torch.tensor(STATS["action_mean"])) / std).tokens
    torch.testing.assert_close(normalised.encode_control(actions).tokens, expected)
    floored = make_model(action_std=[1e-4] * 7)  # an action that never moved in the data is not blown up
    assert floored.control_encoder.std.min() == ACTION_STD_FLOOR


def test_a_model_without_action_statistics_is_refused_at_load(tmp_path):
    make_model(action_mean=None, action_std=None).save_pretrained(tmp_path)
    with pytest.raises(InvalidInputError, match=r"without action statistics.*roboscape-train-wm.*action_mean"):
        STWorldModel.from_pretrained(tmp_path)
    with pytest.raises(InvalidInputError, match=r"action_mean has 6 dimensions.*action_dim=7.*roboscape-train-wm"):
        TinyWorldModelConfig(action_mean=[0.0] * 6, action_std=[1.0] * 6)


@pytest.mark.parametrize("control", ["action", "text"])
def test_dropped_controls_are_the_null_control(control):
    model = make_model(control, control_dropout=0.999).train()
    batch = random_batch()
    other = {**batch, "actions": -batch["actions"], "task": TASKS[::-1]}
    torch.manual_seed(3)
    loss, _ = model(batch)
    torch.manual_seed(3)
    torch.testing.assert_close(model(other)[0], loss)  # nothing of the control is read


def test_guidance_extrapolates_from_the_null_control():
    model = make_model(**CONTROL_PATH)
    batch = random_batch()
    control = model.episode_control(batch["actions"][:, :1, 0])
    prompt = batch["tokens"][:, :1]
    frame = torch.full((2, 1, 8), model.config.mask_token_id)
    first, following = batch["state"][:, :1], batch["state"][:, 1:2]
    guided = Rollout.start(model, prompt, control.frames(slice(0, 1)), states=first)
    logits = guided._logits_of_new_frame(
        frame, guided._paired(control.frames(slice(1, 2))), torch.cat([following, following])
    )
    parts = []
    for c in (control, model.null_control(control)):
        plain = Rollout.start(model, prompt, c.frames(slice(0, 1)), guided=False, states=first)
        parts.append(plain._logits_of_new_frame(frame, c.frames(slice(1, 2)), following))
    torch.testing.assert_close(logits, parts[1] + 2.0 * (parts[0] - parts[1]))


@pytest.mark.parametrize("control", ["action", "text"])
def test_save_load_round_trip(control, tmp_path):
    model = make_model(control)
    model.save_pretrained(tmp_path)
    loaded = STWorldModel.from_pretrained(tmp_path).eval()
    assert vars(loaded.config) == vars(model.config)
    batch = random_batch()
    kw = control_kwargs(model, batch, 3)
    a = model.generate(batch["tokens"][:, :1], 3, **kw)
    b = loaded.generate(batch["tokens"][:, :1], 3, **kw)
    assert torch.equal(a.tokens, b.tokens) and torch.equal(a.done, b.done) and torch.equal(a.state, b.state)


def test_a_frame_per_action_chunk():
    """With frame_skip k, generation takes one action per control step and each frame reads the k actions that
    lead to it, in order."""
    model = make_model(frame_skip=2)
    g = torch.Generator().manual_seed(2)
    prompt, actions = torch.randint(0, 16, (2, 1, 8), generator=g), torch.rand(2, 6, 7, generator=g) * 2 - 1
    tokens, done, _ = model.generate(prompt, 3, actions=actions, states=torch.zeros(2, 1, 3))
    assert tokens.shape == (2, 3, 8) and done.shape == (2, 3)
    control = model.episode_control(actions)
    chunks = torch.cat([torch.zeros(2, 1, 2, 7), actions.reshape(2, 3, 2, 7)], 1)
    no_action = torch.tensor([[True, False, False, False]] * 2)
    torch.testing.assert_close(control.tokens, model.encode_control(chunks, no_action).tokens)
    swapped = actions.reshape(2, 3, 2, 7).flip(2).reshape(2, 6, 7)  # the same actions, in the other order
    assert not torch.allclose(model.episode_control(swapped).tokens[:, 1:], control.tokens[:, 1:])


def test_bad_inputs_are_named():
    model = make_model("action")
    batch = random_batch()
    with pytest.raises(ValueError, match=r"\(B, T, 1, 7\).*\(2, 4, 1, 6\)"):
        model.encode_control(batch["actions"][..., :6])
    chunked = make_model("action", frame_skip=2)
    with pytest.raises(ValueError, match="need 6 actions \\(2 per frame\\)"):
        chunked.generate(batch["tokens"][:, :1], 3, actions=batch["actions"][:, :3, 0])
    with pytest.raises(ValueError, match="need 3 actions"):
        model.generate(batch["tokens"][:, :1], 3, actions=batch["actions"][:, :2, 0])
    with pytest.raises(ValueError, match="frames must have 8 tokens"):
        model.compute_logits(batch["tokens"][..., :5], model.encode_control(batch["actions"]), states=batch["state"])
    with pytest.raises(ValueError, match=r"needs the frames' states \(2, 4, D\), got None"):
        model.compute_logits(batch["tokens"], model.encode_control(batch["actions"]))
    with pytest.raises(ValueError, match="starts a rollout from its prompt frames' states"):
        model.generate(batch["tokens"][:, :1], 3, actions=batch["actions"][:, :3, 0])
    text = make_model("text")
    with pytest.raises(ValueError, match="needs instructions"):
        text.encode_control(actions=batch["actions"])
    with pytest.raises(ValueError, match="prompt_frames"):
        TinyWorldModelConfig(window=4, prompt_frames=4)
    with pytest.raises(ValueError, match="control must be"):
        TinyWorldModelConfig(control="audio")


@pytest.mark.parametrize("control,anchor", [("action", False), ("text", False), ("action", True)])
def test_flops_per_clip_are_the_matmuls_counted(control, anchor):
    """The analytic FLOPs behind MFU equal what PyTorch's FLOP counter sees in a forward pass (attention by the
    math kernel, which it can count)."""
    from torch.nn.attention import SDPBackend, sdpa_kernel
    from torch.utils.flop_counter import FlopCounterMode

    model = make_model(control, tokens_per_side=4, d_model=64, window=5, frame_skip=2, masked_head=False, anchor=anchor)
    batch = random_batch(B=2, T=5, S=32)
    batch["actions"] = torch.rand(2, 5, 2, 7)
    model.encode_control(instructions=batch["task"]) if control == "text" else None  # T5 states cached first
    with torch.no_grad(), sdpa_kernel(SDPBackend.MATH), FlopCounterMode(display=False) as counter:
        model(batch)
    assert counter.get_total_flops() / 2 == model.forward_flops_per_clip()
    assert model.training_flops_per_clip() == 3 * model.forward_flops_per_clip()


def test_a_model_without_state_statistics_is_refused_at_load_with_the_command_that_retrains_it(tmp_path):
    run = tmp_path / "world_model_action"
    make_model(state_mean=None, state_std=None).save_pretrained(run / "pretrained_model")
    (run / "train_config.json").write_text(
        '{"dataset": {"repo_id": "local/demos", "root": "/data/demos"}, "tokenizer": "/runs/tokenizer"}'
    )
    with pytest.raises(
        InvalidInputError,
        match=r"without the robot's state statistics.*roboscape-train-wm --dataset.repo_id=local/demos "
        r"--dataset.root=/data/demos --tokenizer=/runs/tokenizer .*--wm.control=action",
    ):
        STWorldModel.from_pretrained(run / "pretrained_model")
    make_model(state=False).save_pretrained(tmp_path / "no_state")  # a model trained without the channel loads
    assert STWorldModel.from_pretrained(tmp_path / "no_state").robot_state is None


def test_a_position_holds_a_patch_of_codes_masked_and_predicted_together():
    """patch=2 on two 4x4 views: 8 positions of 4 codes; `group` takes each view's 2x2 blocks, `ungroup` puts them
    back; training masks a position's codes together."""
    model = make_model(patch=2, tokens_per_side=4, clean_frame_prob=0.0).train()
    assert model.config.positions_per_frame == 8 and model.pos_emb.shape == (8, 32)
    codes = torch.arange(32).view(1, 1, 32)
    grouped = model.group(codes)
    assert grouped.shape == (1, 1, 8, 4)
    assert grouped[0, 0, 0].tolist() == [0, 1, 4, 5] and grouped[0, 0, 4].tolist() == [16, 17, 20, 21]
    assert torch.equal(model.ungroup(grouped), codes)
    batch = random_batch(B=4, T=4, S=32)
    seen = []
    compute = model.compute_hidden
    model.compute_hidden = lambda tokens, *a, **k: seen.append(tokens) or compute(tokens, *a, **k)
    model(batch)
    masked = model.group(seen[0] == model.config.mask_token_id)  # (B, T, N, 4)
    assert masked.any() and (masked.all(-1) == masked.any(-1)).all()  # whole positions, never part of one
    logits = model.compute_logits(batch["tokens"], model.encode_control(batch["actions"]), states=batch["state"])[0]
    assert logits.shape == (4, 4, 32, 16)


def test_a_quaternion_and_its_negation_read_as_one_state():
    """q and -q are one orientation, and the simulator reports either (24 jumps in the bench's exploration): the
    state channel reads both alike, so such a frame costs the state's loss nothing."""
    mean = torch.zeros(STATE_DIM)
    mean[TCP_QUATERNION] = torch.tensor([0.0, 0.707, 0.707, 0.0])  # the gripper pointing down
    model = make_model(state_dim=STATE_DIM, state_mean=mean.tolist(), state_std=[0.02] * STATE_DIM)
    state = mean + 0.01 * torch.randn(2, 4, STATE_DIM, generator=torch.Generator().manual_seed(0))
    flipped = state.clone()
    flipped[:, 2, TCP_QUATERNION] *= -1
    robot = model.robot_state
    assert torch.equal(robot.normalise(flipped), robot.normalise(state))
    assert robot.normalise(state).abs().max() < 5  # near the mean: the unflipped sign was kept
    features, pooled = torch.randn(2, 4, model.config.d_model), torch.randn(2, 4, model.config.d_model)
    torch.nn.init.normal_(robot.head[-1].weight)  # a head that reads its input
    assert robot.loss(features, flipped, pooled) == robot.loss(features, state, pooled)
