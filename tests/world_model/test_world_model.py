import pytest
import torch

from lerobot_roboscape.world_model.configuration_world_model import PaperWorldModelConfig, TinyWorldModelConfig
from lerobot_roboscape.world_model.modeling_world_model import STWorldModel
from lerobot_roboscape.world_model.rollout import Rollout

MICRO = dict(
    n_cameras=2,
    tokens_per_side=2,
    vocab_size=16,
    d_model=32,
    n_head=2,
    n_layer=2,
    window=4,
    prompt_frames=1,
    done_hidden=32,
)
TASKS = ["push the red cube forward", "pull the red cube back"]


def make_model(control="action", **overrides):
    torch.manual_seed(0)
    return STWorldModel(TinyWorldModelConfig(control=control, **{**MICRO, **overrides})).eval()


def random_batch(B=2, T=4, S=8, V=16, seed=0):
    g = torch.Generator().manual_seed(seed)
    return {
        "tokens": torch.randint(0, V, (B, T, S), generator=g),
        "done": (torch.rand(B, T, generator=g) > 0.5).float(),
        "actions": torch.rand(B, T, 7, generator=g) * 2 - 1,
        "no_action": torch.zeros(B, T, dtype=torch.bool),
        "task": TASKS[:B],
    }


def control_kwargs(model, batch, n):
    if model.config.control == "action":
        return {"actions": batch["actions"][:, :n]}
    return {"instructions": batch["task"]}


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
    logits, done, kvs = model.compute_logits(batch["tokens"], control_tokens)
    assert logits.shape == (2, 4, 8, 16) and done.shape == (2, 4)
    assert len(kvs) == 2 and kvs[0][0].shape == (2 * 8, 2, 4, 16)  # (B * S, heads, T, head_dim)
    loss, logs = model.train()(batch)
    loss.backward()
    assert torch.isfinite(loss) and set(logs) >= {"token_ce", "token_acc", "done_loss"}


@pytest.mark.parametrize("control,add_action", [("action", False), ("action", True), ("text", False)])
def test_future_frames_never_influence_the_past(control, add_action):
    model = make_model(control, add_action=add_action)
    batch = random_batch()
    control_tokens = model.encode_control(batch["actions"], batch["no_action"], batch["task"])
    logits, done, _ = model.compute_logits(batch["tokens"], control_tokens)
    changed = batch["tokens"].clone()
    changed[:, 2:] = (changed[:, 2:] + 5) % 16
    if control == "action":
        batch["actions"][:, 2:] = -batch["actions"][:, 2:]
        control_tokens = model.encode_control(batch["actions"], batch["no_action"])
    logits2, done2, _ = model.compute_logits(changed, control_tokens)
    torch.testing.assert_close(logits2[:, :2], logits[:, :2])
    torch.testing.assert_close(done2[:, :2], done[:, :2])
    assert not torch.allclose(logits2[:, 2:], logits[:, 2:])


@pytest.mark.parametrize("control,add_action", [("action", False), ("action", True), ("text", False)])
def test_cached_generation_equals_recomputing_the_window(control, add_action):
    model = make_model(control, add_action=add_action)
    batch = random_batch(T=4)
    prompt = batch["tokens"][:, :1]
    kw = control_kwargs(model, batch, 3)
    cached, done_cached = model.generate(prompt, 3, use_cache=True, **kw)
    full, done_full = model.generate(prompt, 3, use_cache=False, **kw)
    assert torch.equal(cached, full)
    torch.testing.assert_close(done_cached, done_full)


def test_added_action_reaches_every_token_of_its_frame():
    plain, added = make_model(), make_model(add_action=True)
    batch = random_batch()
    for model in (plain, added):  # no cross-attention path: what remains is the added action
        for block in model.blocks:
            torch.nn.init.zeros_(block.cross.proj.weight)
            torch.nn.init.zeros_(block.cross.proj.bias)
    flipped = -batch["actions"]
    for model, reacts in ((plain, False), (added, True)):
        a = model.compute_logits(batch["tokens"], model.encode_control(batch["actions"], batch["no_action"]))[0]
        b = model.compute_logits(batch["tokens"], model.encode_control(flipped, batch["no_action"]))[0]
        assert (not torch.allclose(a, b)) == reacts


def test_changed_tokens_weigh_more_only_where_frames_change():
    batch = random_batch()
    still = {**batch, "tokens": batch["tokens"][:, :1].expand(-1, 4, -1).clone()}  # every frame the same

    def loss(weight, data):
        torch.manual_seed(1)  # the same masks
        return make_model(changed_token_weight=weight).train()(data)[0]

    torch.testing.assert_close(loss(0.0, still), loss(5.0, still))  # nothing changes: nothing to weigh
    assert not torch.isclose(loss(0.0, batch), loss(5.0, batch))


def test_hidden_context_frames_neither_inform_nor_count():
    model = make_model(context_drop_prob=1.0).train()
    batch = random_batch(T=4)
    torch.manual_seed(3)
    loss, _ = model(batch)
    other = {**batch, "tokens": batch["tokens"].clone()}
    other["tokens"][:, 0] = (other["tokens"][:, 0] + 7) % 16  # frame 0 is always hidden when every clip starts over
    torch.manual_seed(3)
    torch.testing.assert_close(model(other)[0], loss)


@pytest.mark.gpu
def test_cached_generation_on_gpu_equals_recomputing_the_window():
    model = make_model("action", window=6).cuda()
    batch = random_batch(T=6)
    prompt, actions = batch["tokens"][:, :1].cuda(), batch["actions"][:, :5].cuda()
    cached, done_cached = model.generate(prompt, 5, actions=actions, use_cache=True)  # fills the window
    full, done_full = model.generate(prompt, 5, actions=actions, use_cache=False)
    assert torch.equal(cached, full)
    torch.testing.assert_close(done_cached, done_full)


def test_long_rollout_stays_finite_with_a_bounded_cache():
    model = make_model("action")
    g = torch.Generator().manual_seed(1)
    prompt = torch.randint(0, 16, (3, 1, 8), generator=g)
    actions = torch.rand(3, 320, 7, generator=g) * 2 - 1
    tokens, done = model.generate(prompt, 320, actions=actions, temperature=1.0, generator=g)
    assert tokens.shape == (3, 320, 8) and tokens.min() >= 0 and tokens.max() < 16
    assert torch.isfinite(done).all() and (done >= 0).all() and (done <= 1).all()
    first_control = model.frame_control(model.episode_control(actions[:, :1]), slice(0, 1))
    rollout = Rollout.start(model, prompt, first_control)
    control = model.episode_control(actions)
    for t in range(1, 12):
        rollout.predict_next_frame(model.frame_control(control, slice(t, t + 1)))
        # a fixed ring of `window` frames per layer
        assert all(layer.k.shape[2] == 4 for layer in rollout.cache.layers) and rollout.cache.frames == t + 1
        assert rollout.tokens.shape[1] == min(t + 1, 3)


def test_overfits_one_clip():
    model = make_model("action").train()
    batch = random_batch(B=2, T=4, seed=3)
    batch["no_action"][:, 0] = True  # a clip from the start of its episodes, as generate() assumes
    opt = torch.optim.AdamW(model.parameters(), lr=3e-3)
    for _ in range(250):
        loss, logs = model(batch)
        opt.zero_grad()
        loss.backward()
        opt.step()
    model.eval()
    # In a batch, frame t carries the action that led to it; generate() takes actions in the order they were taken.
    tokens, done = model.generate(batch["tokens"][:, :1], 3, actions=batch["actions"][:, 1:])
    assert (tokens == batch["tokens"][:, 1:]).float().mean() > 0.95
    assert (done - batch["done"][:, 1:]).abs().max() < 0.2


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
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])


def test_bad_inputs_are_named():
    model = make_model("action")
    batch = random_batch()
    with pytest.raises(ValueError, match=r"\(B, T, 7\).*\(2, 4, 6\)"):
        model.encode_control(batch["actions"][..., :6])
    with pytest.raises(ValueError, match="need 3 actions"):
        model.generate(batch["tokens"][:, :1], 3, actions=batch["actions"][:, :2])
    with pytest.raises(ValueError, match="frames must have 8 tokens"):
        model.compute_logits(batch["tokens"][..., :5], model.encode_control(batch["actions"]))
    text = make_model("text")
    with pytest.raises(ValueError, match="needs instructions"):
        text.encode_control(actions=batch["actions"])
    with pytest.raises(ValueError, match="prompt_frames"):
        TinyWorldModelConfig(window=4, prompt_frames=4)
    with pytest.raises(ValueError, match="control must be"):
        TinyWorldModelConfig(control="audio")
