"""A world model's training loss: which tokens it weighs, its masked head paths, and the context it corrupts."""

import pytest
import torch

from tests.world_model.micro import TASKS, make_model, random_batch


@pytest.mark.parametrize("changed_weight", [1.0, 7.0])
def test_changed_tokens_weigh_changed_weight_in_the_token_loss(changed_weight):
    model = make_model(changed_weight=changed_weight, clean_frame_prob=0.0, done_weight=0.0).train()
    batch = random_batch()
    batch["tokens"][:, 2] = batch["tokens"][:, 1]  # frame 2 copies frame 1: none of its tokens changed
    seen = []
    compute = model.compute_hidden
    model.compute_hidden = lambda tokens, *a, **k: (
        seen.append((tokens, model.token_logits(compute(tokens, *a, **k)[0]))) or compute(tokens, *a, **k)
    )
    loss, metrics = model(batch)
    loss = loss - metrics["state_mse"]  # the state's own loss, beside the tokens'
    inputs, logits = seen[0]
    tokens = batch["tokens"]
    mask = inputs == model.config.mask_token_id
    changed = torch.zeros_like(mask)
    changed[:, 1:] = tokens[:, 1:] != tokens[:, :-1]
    assert (mask & changed).any() and (mask & ~changed).any()
    ce = torch.nn.functional.cross_entropy(logits[mask], tokens[mask], reduction="none")
    weight = 1.0 + (changed_weight - 1.0) * changed[mask].float()
    torch.testing.assert_close(loss, (weight * ce).sum() / weight.sum())
    hits = logits[mask].argmax(-1) == tokens[mask]
    assert metrics["changed_acc"] == pytest.approx(hits[changed[mask]].float().mean().item())


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
    tokens, done, states = model.generate(
        batch["tokens"][:, :1], 3, actions=batch["actions"][:, 1:, 0], states=batch["state"][:, :1]
    )
    assert (tokens == batch["tokens"][:, 1:]).float().mean() > 0.95
    assert (done - batch["done"][:, 1:]).abs().max() < 0.2
    assert (states - batch["state"][:, 1:]).abs().max() < 0.2  # the state fed back, frame after frame


@pytest.mark.parametrize("masked_head", [True, False])
@pytest.mark.parametrize("control", ["action", "text"])
def test_loss_is_the_masked_mean_whether_the_head_reads_the_masked_positions_or_all(control, masked_head):
    """The loss equals its definition, the head run on the masked positions only (the CPU's path) or on every
    position with weights (no boolean indexing, so no host sync): the token cross-entropy averaged over the masked
    tokens, changed ones weighing changed_weight, plus the class-balanced done loss; its logs are tensors the
    training loop reads on logging steps only."""
    model = make_model(control, changed_weight=3.0, clean_frame_prob=0.0, masked_head=masked_head).train()
    batch = random_batch(B=4, T=4, S=8)
    batch["done"][:] = 0.0
    batch["done"][0, 3] = 1.0  # one rare positive
    batch["task"] = TASKS * 2
    torch.manual_seed(7)
    loss, logs = model(batch)
    assert all(torch.is_tensor(v) and not v.requires_grad for v in logs.values())
    # The same draw of masks, then the definition with boolean indexing.
    torch.manual_seed(7)
    tokens = batch["tokens"]
    B, T, S = tokens.shape
    ratio = torch.cos(torch.pi / 2 * torch.rand(B, T, 1)) * (torch.rand(B, T, 1) >= 0.0)
    ratio[:, 0] = 0.0
    mask = torch.rand(B, T, S) < ratio
    control_tokens = model.encode_control(batch["actions"], batch["no_action"], batch["task"])
    inputs = tokens.masked_fill(mask, model.config.mask_token_id)
    logits, done_logits, _ = model.compute_logits(inputs, control_tokens, states=batch["state"])
    changed = torch.zeros_like(mask)
    changed[:, 1:] = tokens[:, 1:] != tokens[:, :-1]
    ce = torch.nn.functional.cross_entropy(logits[mask], tokens[mask], reduction="none")
    weight = torch.where(changed[mask], 3.0, 1.0)
    bce = torch.nn.functional.binary_cross_entropy_with_logits(done_logits, batch["done"], reduction="none")
    positive = batch["done"] > 0.5
    expected = (weight * ce).sum() / weight.sum() + (bce[positive].mean() + bce[~positive].mean()) / 2
    torch.testing.assert_close(loss, expected + logs["state_mse"])  # the state's own loss beside them
    hits = logits[mask].argmax(-1) == tokens[mask]
    torch.testing.assert_close(logs["token_acc"], hits.float().mean())
    torch.testing.assert_close(logs["changed_acc"], hits[changed[mask]].float().mean())


def test_both_head_paths_give_the_same_gradients():
    """The masked positions' head (the CPU's default) trains the model as the weighted one does."""
    grads = []
    for masked_head in (True, False):
        torch.manual_seed(0)
        model = make_model(changed_weight=5.0, patch=2, tokens_per_side=4, masked_head=masked_head).train()
        batch = random_batch(B=3, T=4, S=32)
        torch.manual_seed(1)
        loss, _ = model(batch)
        loss.backward()
        grads.append({n: p.grad.clone() for n, p in model.named_parameters() if p.grad is not None})
    assert grads[0].keys() == grads[1].keys()
    for name, grad in grads[0].items():
        torch.testing.assert_close(grad, grads[1][name], msg=name)


def test_training_corrupts_a_share_of_the_unmasked_context_drawn_per_clip():
    model = make_model(corrupt_max=0.9, clean_frame_prob=0.0).train()
    batch = random_batch(B=64, T=4)
    seen = []
    compute = model.compute_hidden
    model.compute_hidden = lambda tokens, *a, **k: seen.append(tokens) or compute(tokens, *a, **k)
    torch.manual_seed(0)
    model(batch)
    inputs, tokens = seen[0], batch["tokens"]
    unmasked = inputs != model.config.mask_token_id
    replaced = (inputs != tokens) & unmasked  # a random code may equal the true one: a lower bound of the rate
    share = replaced.flatten(1).sum(1) / unmasked.flatten(1).sum(1)
    assert share.max() > 0.4 and share.min() < 0.15  # drawn per clip in [0, 0.9], 15/16 of draws visible
    assert (inputs[:, 0] != model.config.mask_token_id).all()  # the prompt is never masked, only corrupted
    model.compute_hidden = compute
    plain = make_model(clean_frame_prob=0.0).train()
    seen.clear()
    plain.compute_hidden = lambda tokens, *a, **k: seen.append(tokens) or compute(tokens, *a, **k)
    plain(batch)
    assert ((seen[0] == tokens) | (seen[0] == plain.config.mask_token_id)).all()  # corrupt_max=0: none


def test_held_corruption_replaces_the_same_codes_by_the_same_codes_in_every_frame():
    model = make_model(corrupt_max=0.9, corrupt_held=True).train()
    batch = random_batch(B=64, T=4)
    batch["tokens"][:] = batch["tokens"][:, :1]  # a still clip: a frame's codes are the first's
    seen = []
    compute = model.compute_hidden
    model.compute_hidden = lambda tokens, *a, **k: seen.append(tokens) or compute(tokens, *a, **k)
    model(batch)
    inputs = seen[0]
    unmasked = inputs != model.config.mask_token_id
    assert ((inputs == inputs[:, :1]) | ~unmasked).all()  # every frame wrong where the first is, and alike
    share = ((inputs != batch["tokens"]) & unmasked)[:, 0].float().mean(1)
    assert share.max() > 0.4 and share.min() < 0.15
