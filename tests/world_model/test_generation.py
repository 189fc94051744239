"""Generation from a world model: the key/value cache against recomputing the window, CUDA graphs, sampling, the
anchor past the window, and long rollouts."""

import pytest
import torch

from lerobot_roboscape.world_model.rollout import Rollout
from tests.world_model.micro import CONTROL_PATH, VARIANTS, control_kwargs, make_model, random_batch


@pytest.mark.parametrize("control,overrides", VARIANTS)
def test_cached_generation_equals_recomputing_the_window(control, overrides):
    """Guided, each half (under the control, under the null control) keeps its own cache."""
    model = make_model(control, **overrides)
    batch = random_batch(T=4)
    prompt = batch["tokens"][:, :1]
    kw = control_kwargs(model, batch, 3)
    cached, done_cached, state_cached = model.generate(
        prompt, 3, use_cache=True, generator=torch.Generator().manual_seed(0), **kw
    )
    full, done_full, state_full = model.generate(
        prompt, 3, use_cache=False, generator=torch.Generator().manual_seed(0), **kw
    )
    assert torch.equal(cached, full)
    torch.testing.assert_close(done_cached, done_full)
    torch.testing.assert_close(state_cached, state_full)


def test_sampled_decoding_is_reproducible_from_its_generator():
    model = make_model(maskgit_steps=3)
    batch = random_batch()
    kw = control_kwargs(model, batch, 3)
    runs = [
        model.generate(batch["tokens"][:, :1], 3, temperature=1.0, generator=torch.Generator().manual_seed(s), **kw)[0]
        for s in (0, 0, 1)
    ]
    assert torch.equal(runs[0], runs[1]) and not torch.equal(runs[0], runs[2])
    assert runs[0].min() >= 0 and runs[0].max() < 16


@pytest.mark.gpu
def test_cached_generation_on_gpu_equals_recomputing_the_window():
    model = make_model("action", window=6).cuda()
    batch = random_batch(T=6)
    prompt, actions = batch["tokens"][:, :1].cuda(), batch["actions"][:, :5, 0].cuda()
    states = batch["state"][:, :1].cuda()
    cached, done_cached, _ = model.generate(
        prompt, 5, actions=actions, use_cache=True, states=states
    )  # fills the window
    full, done_full, _ = model.generate(prompt, 5, actions=actions, use_cache=False, states=states)
    assert torch.equal(cached, full)
    torch.testing.assert_close(done_cached, done_full)


def test_a_new_episode_refilling_a_used_cache_generates_what_a_fresh_cache_does():
    """A reused cache's rings hold the last episode's frames past the new prompt: none may leak in."""
    model = make_model("action", **CONTROL_PATH)
    batch = random_batch(T=4)
    control = model.episode_control(batch["actions"][:, :6, 0].repeat(1, 2, 1))

    def episode(reuse=None):
        rollout = Rollout.start(
            model, batch["tokens"][:, :1], control.frames(slice(0, 1)), reuse=reuse, states=batch["state"][:, :1]
        )
        frames = [rollout.predict_next_frame(control.frames(slice(t, t + 1)))[0] for t in range(1, 6)]
        return rollout, torch.stack(frames, 1)

    first, reference = episode()
    rings = [layer.k for layer in first.cache.layers]
    second, again = episode(reuse=first)
    assert second.cache is first.cache
    assert all(a is b.k for a, b in zip(rings, second.cache.layers, strict=True))  # the same rings, refilled
    assert torch.equal(again, reference)


def test_capture_needs_the_cache_on_a_cuda_device():
    model = make_model("action")
    batch = random_batch()
    with pytest.raises(ValueError, match="capture needs the key/value cache on a CUDA device"):
        model.generate(batch["tokens"][:, :1], 2, capture=True, **control_kwargs(model, batch, 2))


@pytest.mark.gpu
@pytest.mark.parametrize("control,overrides", VARIANTS)
@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
def test_captured_generation_on_gpu_gives_the_uncaptured_tokens(control, overrides, dtype):
    """Past the window (the ring wraps), guided or not, each decoding order, under autocast or not."""
    model = make_model(control, **overrides).cuda()
    batch = random_batch(T=4)
    prompt = batch["tokens"][:, :1].cuda()
    kw = {k: v.cuda() if torch.is_tensor(v) else v for k, v in control_kwargs(model, batch, 1).items()}
    if control == "action":
        kw["actions"] = (torch.rand(2, 9, 7, generator=torch.Generator().manual_seed(2)) * 2 - 1).cuda()
    runs = []
    for capture in (False, True):
        generator = torch.Generator("cuda").manual_seed(0)
        with torch.autocast("cuda", torch.bfloat16, enabled=dtype == torch.bfloat16):
            runs.append(model.generate(prompt, 9, capture=capture, generator=generator, **kw))
    assert torch.equal(runs[0][0], runs[1][0])
    torch.testing.assert_close(runs[0][1], runs[1][1])
    torch.testing.assert_close(runs[0][2], runs[1][2])


@pytest.mark.parametrize("use_cache", [True, False])
@pytest.mark.parametrize("guided", [False, True])
def test_an_anchored_rollout_reads_its_first_frame_after_the_window_has_lost_it(guided, use_cache):
    model = make_model("action", anchor=True, **(CONTROL_PATH if guided else {}))
    batch = random_batch(T=4)
    control = model.episode_control(torch.rand(2, 9, 7, generator=torch.Generator().manual_seed(4)) * 2 - 1)
    prompt = batch["tokens"][:, :1]
    rollout = Rollout.start(model, prompt, control.frames(slice(0, 1)), use_cache, states=batch["state"][:, :1])
    for t in range(1, 8):
        rollout.predict_next_frame(control.frames(slice(t, t + 1)))
    assert rollout.tokens.shape[1] == 3 and torch.equal(rollout.anchor[:2], prompt[:, 0])  # the window: 3 + new
    before = rollout.next_frame_logits(control.frames(slice(8, 9)))
    rollout.anchor = (rollout.anchor + 1) % 16
    assert not torch.allclose(before, rollout.next_frame_logits(control.frames(slice(8, 9))))


def _copy_clips(step: int, B: int = 16) -> dict:
    """Clips [R, A] of episodes A, R, A, ...: the scene the episode started in comes back after the window (2
    frames) has lost it; only the anchor still shows it."""
    batch = random_batch(B=B, T=2, seed=step)
    batch["anchor"] = batch["tokens"][:, 1].clone()
    batch["no_action"][:, 0] = True
    return batch


@pytest.mark.slow
def test_an_anchored_model_learns_to_redraw_what_left_its_window_and_a_plain_one_cannot():
    accuracy = {}
    for anchor in (False, True):
        model = make_model("action", anchor=anchor, window=2, clean_frame_prob=0.0).train()
        opt = torch.optim.AdamW(model.parameters(), lr=3e-3)
        for step in range(1000):  # the copy is learnt between steps 300 and 600 (measured, 3 seeds); plain: 0.06
            loss, _ = model(_copy_clips(step))
            opt.zero_grad()
            loss.backward()
            opt.step()
        episodes = _copy_clips(10_000, B=64)
        start, control = episodes["tokens"][:, 1:2], model.eval().episode_control(episodes["actions"][:, :2, 0])
        rollout = Rollout.start(model, start, control.frames(slice(0, 1)), states=episodes["state"][:, :1])
        rollout.observe(episodes["tokens"][:, :1], control.frames(slice(1, 2)), episodes["state"][:, 0])
        frame, _ = rollout.predict_next_frame(control.frames(slice(2, 3)))
        accuracy[anchor] = (frame == start[:, 0]).float().mean().item()
    assert accuracy[True] > 0.9 and accuracy[False] < 0.2  # chance: 1 / 16


def test_long_rollout_stays_finite_with_a_bounded_cache():
    model = make_model("action")
    g = torch.Generator().manual_seed(1)
    prompt = torch.randint(0, 16, (3, 1, 8), generator=g)
    actions = torch.rand(3, 320, 7, generator=g) * 2 - 1
    first = torch.randn(3, 1, 3, generator=g)
    tokens, done, states = model.generate(prompt, 320, actions=actions, temperature=1.0, generator=g, states=first)
    assert tokens.shape == (3, 320, 8) and tokens.min() >= 0 and tokens.max() < 16
    assert torch.isfinite(done).all() and (done >= 0).all() and (done <= 1).all()
    assert states.shape == (3, 320, 3) and torch.isfinite(states).all()
    first_control = model.episode_control(actions[:, :1]).frames(slice(0, 1))
    rollout = Rollout.start(model, prompt, first_control, states=first)
    control = model.episode_control(actions)
    for t in range(1, 12):
        rollout.predict_next_frame(control.frames(slice(t, t + 1)))
        # a fixed ring of `window` frames per layer
        assert all(layer.k.shape[2] == 4 for layer in rollout.cache.layers) and rollout.cache.frames == t + 1
        assert rollout.tokens.shape[1] == min(t + 1, 3)


@pytest.mark.parametrize("guided", [False, True])
@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
def test_cache_holds_what_cache_bytes_says_in_the_compute_dtype(guided, dtype):
    """A rollout's key/value cache is its rings alone, in the dtype the model computes in, of the size cache_bytes
    estimates; a prompt longer than the window keeps its last window - 1 frames."""
    from lerobot_roboscape.world_model.rollout import Rollout

    overrides = dict(control_dropout=0.1, guidance_scale=2.0) if guided else {}
    model = make_model(**overrides)
    batch = random_batch(B=3, T=6)
    control = model.episode_control(batch["actions"][:, :5, 0])
    with torch.autocast("cpu", torch.bfloat16, enabled=dtype == torch.bfloat16):
        rollout = Rollout.start(model, batch["tokens"], control, states=batch["state"])
    cache = rollout.cache
    assert {ring.k.dtype for ring in cache.layers} == {dtype} and len(cache.layers) == model.config.n_layer
    assert cache.allocated_bytes == model.cache_bytes(3, dtype)
    assert cache.frames == 6 and cache.layers[0].k.shape[2] == model.config.window
