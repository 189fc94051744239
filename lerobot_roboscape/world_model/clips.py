"""Training clips for the world models, sampled from a token cache."""

import numpy as np
import torch

from lerobot_roboscape.errors import InvalidInputError
from lerobot_roboscape.tokenizer.token_cache import TokenCache


def select_episodes(
    cache: TokenCache, episodes: list[int] | None = None, only_optimal: bool = False, only_successful: bool = False
) -> list[dict]:
    """Episodes of the cache kept for training. Episodes without roboscape facts (converted datasets) count as
    optimal; their success is read from the done labels."""
    known = {row["episode_index"] for row in cache.episodes}
    if episodes is not None and (missing := sorted(set(episodes) - known)):
        raise InvalidInputError(
            f"episodes {missing} are not in the token cache {cache.root} (it has {len(known)} episodes)"
        )
    rows = []
    for row in cache.episodes:
        if episodes is not None and row["episode_index"] not in episodes:
            continue
        if only_optimal and not row.get("optimal", True):
            continue
        succeeded = row.get("success", bool(cache.done[row["start"] : row["start"] + row["length"]].max() > 0.5))
        if only_successful and not succeeded:
            continue
        rows.append(row)
    if not rows:
        raise InvalidInputError(
            f"no episodes of {cache.root} left for training (episodes={episodes}, "
            f"only_optimal={only_optimal}, only_successful={only_successful})"
        )
    return rows


def model_frames(length: int, frame_skip: int) -> np.ndarray:
    """Control steps of an episode of `length` steps that are model frames: every k-th from the first."""
    return np.arange(0, length, frame_skip)


class ClipSampler:
    """Batches of `window`-frame clips, a pure function of (step, process) so that resumed runs repeat them.

    Clip frames are `frame_skip` (k) control steps apart, from any step of the episode. Each clip's frame t carries
    the k actions taken from frame t - 1 (the first frame of an episode has none: `no_action`). Actions before the
    episode's start or past its last step are zeros, and episodes shorter than the clip hold their last frame still.
    """

    def __init__(
        self,
        cache: TokenCache,
        episodes: list[dict],
        window: int,
        batch_size: int,
        seed: int = 0,
        frame_skip: int = 1,
    ):
        self.cache, self.episodes, self.window, self.batch_size, self.seed = cache, episodes, window, batch_size, seed
        self.frame_skip = frame_skip
        lengths = np.array([row["length"] for row in episodes], dtype=np.float64)
        self.weights = lengths / lengths.sum()

    def __call__(self, step: int, process_index: int = 0) -> dict:
        rng = np.random.default_rng([self.seed, step, process_index])
        return collate([self.random_clip(rng) for _ in range(self.batch_size)])

    def random_clip(self, rng: np.random.Generator) -> dict:
        """A clip from an episode drawn in proportion to its length."""
        return self.clip(self.episodes[rng.choice(len(self.episodes), p=self.weights)], rng)

    def clip(self, row: dict, rng: np.random.Generator) -> dict:
        start, length, k = row["start"], row["length"], self.frame_skip
        span = (self.window - 1) * k + 1  # control steps a clip covers
        offset = int(rng.integers(0, max(1, length - span + 1)))
        frames = np.minimum(offset + k * np.arange(self.window), length - 1)  # hold the last frame if short
        tokens = self.cache.tokens[start + frames].reshape(self.window, -1)  # views side by side: (T, S)
        steps = offset + k * (np.arange(self.window)[:, None] - 1) + np.arange(k)  # (T, k): the actions of frame t
        valid = (steps >= 0) & (steps < length - 1)
        actions = np.where(valid[..., None], self.cache.actions[start + np.clip(steps, 0, length - 1)], 0.0)
        return {
            "tokens": tokens.astype(np.int64),
            "actions": actions.astype(np.float32),  # (T, k, A)
            "no_action": (steps < 0).all(axis=1),
            "done": np.asarray(self.cache.done[start + frames], dtype=np.float32),
            "reward": np.asarray(self.cache.rewards[start + frames], dtype=np.float32),
            "task": row["task"],
        }


class ClipMixture:
    """Batches of clips from several samplers (of their own token caches): each clip comes from sampler i with
    probability shares[i]. A pure function of (step, process), as ClipSampler."""

    def __init__(self, samplers: list[ClipSampler], shares: list[float], batch_size: int, seed: int = 0):
        if len(samplers) != len(shares) or abs(sum(shares) - 1) > 1e-6 or min(shares) < 0:
            raise InvalidInputError(f"shares {shares} must be one per sampler, >= 0, summing to 1")
        self.samplers, self.shares, self.batch_size, self.seed = samplers, shares, batch_size, seed

    def __call__(self, step: int, process_index: int = 0) -> dict:
        rng = np.random.default_rng([self.seed, step, process_index])
        sources = rng.choice(len(self.samplers), size=self.batch_size, p=self.shares)
        return collate([self.samplers[i].random_clip(rng) for i in sources])


def collate(clips: list[dict]) -> dict:
    batch = {key: torch.from_numpy(np.stack([c[key] for c in clips])) for key in clips[0] if key != "task"}
    batch["tokens"] = batch["tokens"].long()
    batch["task"] = [c["task"] for c in clips]
    return batch
