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


class ClipSampler:
    """Batches of `window`-frame clips, a pure function of (step, process) so that resumed runs repeat them.

    Each clip's frame t carries the action taken in frame t - 1 (the first frame of an episode has none).
    Episodes shorter than the window are padded with their last frame held still (zero action).
    """

    def __init__(self, cache: TokenCache, episodes: list[dict], window: int, batch_size: int, seed: int = 0):
        self.cache, self.episodes, self.window, self.batch_size, self.seed = cache, episodes, window, batch_size, seed
        lengths = np.array([row["length"] for row in episodes], dtype=np.float64)
        self.weights = lengths / lengths.sum()

    def __call__(self, step: int, process_index: int = 0) -> dict:
        rng = np.random.default_rng([self.seed, step, process_index])
        picks = rng.choice(len(self.episodes), size=self.batch_size, p=self.weights)
        clips = [self.clip(self.episodes[i], rng) for i in picks]
        batch = {key: torch.from_numpy(np.stack([c[key] for c in clips])) for key in clips[0] if key != "task"}
        batch["tokens"] = batch["tokens"].long()
        batch["task"] = [c["task"] for c in clips]
        return batch

    def clip(self, row: dict, rng: np.random.Generator) -> dict:
        start, length = row["start"], row["length"]
        offset = int(rng.integers(0, max(1, length - self.window + 1)))
        frames = np.minimum(np.arange(offset, offset + self.window), length - 1)  # hold the last frame if short
        tokens = self.cache.tokens[start + frames].reshape(self.window, -1)  # views side by side: (T, S)
        prev = offset + np.arange(self.window) - 1
        valid = (prev >= 0) & (prev < length - 1)
        actions = np.where(valid[:, None], self.cache.actions[start + np.clip(prev, 0, length - 1)], 0.0)
        return {
            "tokens": tokens.astype(np.int64),
            "actions": actions.astype(np.float32),
            "no_action": prev < 0,
            "done": np.asarray(self.cache.done[start + frames], dtype=np.float32),
            "reward": np.asarray(self.cache.rewards[start + frames], dtype=np.float32),
            "task": row["task"],
        }
