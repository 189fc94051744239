"""The done head trained where it is read: on the action model's own open-loop frames.

Training teaches the done head on real frames, mostly masked ones. Inside `roboscape_wm` it reads frames the model
generated, which drift from the real ones, and a head that never saw such frames need not fire on them. After the
model is trained, this stage generates training episodes open loop from their first frames and recorded actions, and
fits the done head alone (so generation is unchanged) on the final hidden states of those frames and of the real
ones read teacher-forced, labelled with each real frame's done label. The pooled hidden states are what the head
reads, so they are computed once and the head trains on them in seconds.
"""

import logging
from dataclasses import dataclass

import numpy as np
import torch

from lerobot_roboscape.tokenizer.token_cache import TokenCache
from lerobot_roboscape.world_model.clips import model_frames
from lerobot_roboscape.world_model.modeling_world_model import STWorldModel
from lerobot_roboscape.world_model.rollout import Rollout

logger = logging.getLogger(__name__)


@torch.no_grad()
def done_features(
    model: STWorldModel, cache: TokenCache, episodes: list[dict], batch_size: int = 16
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The done head's inputs of every model frame after the prompt of `episodes`, open loop and teacher-forced:
    features (N, C), done labels (N,), and whether each row is open loop (N,) bool."""
    P, k = model.config.prompt_frames, model.config.frame_skip
    device = next(model.parameters()).device
    rows = [r for r in episodes if len(model_frames(r["length"], k)) > P]
    rows.sort(key=lambda r: r["length"])  # batches of similar lengths pad less
    features, labels, open_loop = [], [], []
    for first in range(0, len(rows), batch_size):
        batch = rows[first : first + batch_size]
        frames = [r["start"] + model_frames(r["length"], k) for r in batch]
        T = max(len(f) for f in frames)
        # Shorter episodes hold their last frame and action: their padded frames are left out below.
        held = [np.concatenate([f, np.repeat(f[-1:], T - len(f))]) for f in frames]
        tokens = torch.from_numpy(np.stack([cache.tokens[f].reshape(T, -1) for f in held]).astype(np.int64))
        states = torch.from_numpy(np.stack([cache.states[f] for f in held])).float().to(device)
        steps = [r["start"] + np.minimum(np.arange((T - 1) * k), r["length"] - 1) for r in batch]
        actions = torch.from_numpy(np.stack([cache.actions[s] for s in steps])).float()
        tokens, actions = tokens.to(device), actions.to(device)
        generated = _open_loop_features(model, tokens[:, :P], T - P, actions, states[:, :P])
        _, forced = model.teacher_forced(tokens, actions, states=states)
        for i, f in enumerate(frames):
            n = len(f) - P
            done = torch.from_numpy(np.asarray(cache.done[f[P:]], dtype=np.float32))
            features += [generated[i, :n].float().cpu(), forced[i, P : P + n].float().cpu()]
            labels += [done, done]
            open_loop += [torch.ones(n, dtype=torch.bool), torch.zeros(n, dtype=torch.bool)]
        logger.info("done features: %d/%d episodes", min(first + batch_size, len(rows)), len(rows))
    return torch.cat(features), torch.cat(labels), torch.cat(open_loop)


def _open_loop_features(model: STWorldModel, prompt_BPS, n_frames: int, actions, states_BPD) -> torch.Tensor:
    """(B, n_frames, C): the done head's input at each frame the model generates."""
    P = prompt_BPS.shape[1]
    control = model.episode_control(actions)
    rollout = Rollout.start(model, prompt_BPS, control.frames(slice(0, P)), guided=True, states=states_BPD)
    features = []
    for t in range(P, P + n_frames):
        rollout.predict_next_frame(control.frames(slice(t, t + 1)))
        features.append(rollout.features)
    return torch.stack(features, 1)


def tune_done_head(
    model: STWorldModel, features: torch.Tensor, labels: torch.Tensor, steps: int = 300, lr: float = 1e-3
) -> list[float]:
    """Fit the done head alone on (features, labels) with the model's done loss, full batch; returns the losses."""
    head = model.done_head
    device = next(head.parameters()).device
    features, labels = features.to(device), labels.to(device)
    optimizer = torch.optim.AdamW(head.parameters(), lr=lr, weight_decay=0.01)
    losses = []
    head.train()
    for _ in range(steps):
        loss = model.done_loss(head(features).squeeze(-1).float(), labels)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        losses.append(loss.item())
    head.eval()
    return losses


@dataclass(frozen=True)
class SourceFit:
    """One source's frames and positives in a refit, and the head's mean output after it on its open-loop positive
    and negative frames (None where it has none)."""

    frames: int
    positives: int
    done_of_open_loop_positives: float | None
    done_of_open_loop_negatives: float | None


@dataclass(frozen=True)
class RefitFigures:
    """A refit's loss, first and last step ({"first", "last"}), and each source's figures in the order given."""

    loss: dict[str, float]
    sources: list[SourceFit]


def refit_done_head(
    model: STWorldModel,
    sources: list[tuple[TokenCache, list[dict]]],
    steps: int,
) -> RefitFigures:
    """Refit the done head on the open-loop and real frames of the episodes of every (cache, episodes) source (the
    policy's simulator rollouts beside demonstrations, so the head keeps what it knew); returns the fit's figures
    per source: frames, positives, and the head's mean output on open-loop positives / negatives after the fit."""
    model.eval()
    parts = [done_features(model, cache, episodes) for cache, episodes in sources]
    features, labels = torch.cat([p[0] for p in parts]), torch.cat([p[1] for p in parts])
    losses = tune_done_head(model, features, labels, steps)
    device = next(model.parameters()).device
    figures = []
    with torch.no_grad():
        for source_features, source_labels, open_loop in parts:
            after = torch.sigmoid(model.done_head(source_features.to(device)).squeeze(-1)).cpu()
            positive, negative = open_loop & (source_labels > 0.5), open_loop & (source_labels <= 0.5)
            figures.append(
                SourceFit(
                    len(source_labels),
                    int((source_labels > 0.5).sum()),
                    float(after[positive].mean()) if positive.any() else None,
                    float(after[negative].mean()) if negative.any() else None,
                )
            )
    return RefitFigures({"first": losses[0], "last": losses[-1]}, figures)
