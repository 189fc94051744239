"""Training clips for the world models, sampled from a token cache: on the host (ClipSampler, ClipMixture) or sliced
where the model trains from the caches held there whole (ResidentClips)."""

from dataclasses import dataclass

import numpy as np
import torch
from lerobot.utils.constants import SUCCESS

from lerobot_roboscape.tokenizer.token_cache import TokenCache
from roboscape_core.errors import InvalidInputError


def select_episodes(
    cache: TokenCache, episodes: list[int] | None = None, only_optimal: bool = False, only_successful: bool = False
) -> list[dict]:
    """Episodes of the cache kept for training. Episodes without roboscape facts (converted datasets) count as
    optimal; their success is read from `next.success` labels, and where the dataset has none (a user's recordings,
    whose `next.done` marks only an episode's end) they count as successful: demonstrations."""
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
        done = cache.done[row["start"] : row["start"] + row["length"]]
        succeeded = row.get("success", bool(done.max() > 0.5) if cache.done_column == SUCCESS else True)
        if only_successful and not succeeded:
            continue
        rows.append(row)
    if not rows:
        raise InvalidInputError(
            f"no episodes of {cache.root} left for training (episodes={episodes}, "
            f"only_optimal={only_optimal}, only_successful={only_successful}: --only_optimal=false and "
            "--only_successful=false keep every episode)"
        )
    return rows


def model_frames(length: int, frame_skip: int) -> np.ndarray:
    """Control steps of an episode of `length` steps that are model frames: every k-th from the first."""
    return np.arange(0, length, frame_skip)


@dataclass
class ClipIndex:
    """Where a batch of clips lies in a token cache's arrays: the rows of its frames and of its actions."""

    rows: np.ndarray  # (B, T) the rows of the clip's frames
    action_rows: np.ndarray  # (B, T, k) the rows of the k actions leading to each frame
    valid: np.ndarray  # (B, T, k) bool: False for actions before the episode's start or past its last step
    no_action: np.ndarray  # (B, T) bool: frames with no action before them (an episode's first frame)
    tasks: list[str]
    anchor_rows: np.ndarray  # (B,) the row of each clip's episode's first frame (an anchored model reads it)

    @staticmethod
    def cat(parts: list["ClipIndex"], offsets: list[int]) -> "ClipIndex":
        """The clips of several caches, in order, with each one's rows moved by its cache's offset in a
        concatenation of the caches."""
        return ClipIndex(
            np.concatenate([p.rows + o for p, o in zip(parts, offsets, strict=True)]),
            np.concatenate([p.action_rows + o for p, o in zip(parts, offsets, strict=True)]),
            np.concatenate([p.valid for p in parts]),
            np.concatenate([p.no_action for p in parts]),
            [task for p in parts for task in p.tasks],
            np.concatenate([p.anchor_rows + o for p, o in zip(parts, offsets, strict=True)]),
        )


class ClipSampler:
    """Batches of `window`-frame clips, a pure function of (step, process) so that resumed runs repeat them.

    Clip frames are `frame_skip` (k) control steps apart, from any step of the episode. Each clip's frame t carries
    the k actions taken from frame t - 1 (the first frame of an episode has none: `no_action`). Actions before the
    episode's start or past its last step are zeros, and episodes shorter than the clip hold their last frame still.
    Episodes are drawn in proportion to their length.
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
        self.starts = np.array([row["start"] for row in episodes], dtype=np.int64)
        self.lengths = np.array([row["length"] for row in episodes], dtype=np.int64)
        self.weights = self.lengths / self.lengths.sum()
        self.caches = [cache]

    def __call__(self, step: int, process_index: int = 0) -> dict:
        return gather(self.cache, self.index(step, process_index))

    def index(self, step: int, process_index: int = 0) -> ClipIndex:
        return self.draw(np.random.default_rng([self.seed, step, process_index]), self.batch_size)

    def draw(self, rng: np.random.Generator, n: int) -> ClipIndex:
        """n clips: their episodes, then their first control steps."""
        T, k = self.window, self.frame_skip
        picked = rng.choice(len(self.episodes), size=n, p=self.weights)
        start, length = self.starts[picked, None], self.lengths[picked, None]
        span = (T - 1) * k + 1  # control steps a clip covers
        offset = rng.integers(0, np.maximum(1, length - span + 1))  # (n, 1)
        frames = np.minimum(offset + k * np.arange(T), length - 1)  # hold the last frame if short: (n, T)
        steps = offset[..., None] + k * (np.arange(T)[:, None] - 1) + np.arange(k)  # (n, T, k): actions of frame t
        return ClipIndex(
            rows=start + frames,
            action_rows=start[..., None] + np.clip(steps, 0, length[..., None] - 1),
            valid=(steps >= 0) & (steps < length[..., None] - 1),
            no_action=(steps < 0).all(axis=2),
            tasks=[self.episodes[i]["task"] for i in picked],
            anchor_rows=start[:, 0],
        )


class ClipMixture:
    """Batches of clips from several samplers (of their own token caches): each clip comes from sampler i with
    probability shares[i]. A pure function of (step, process), as ClipSampler. Its rows index the concatenation of
    the samplers' caches, in order (`caches`)."""

    def __init__(self, samplers: list[ClipSampler], shares: list[float], batch_size: int, seed: int = 0):
        if len(samplers) != len(shares) or abs(sum(shares) - 1) > 1e-6 or min(shares) < 0:
            raise InvalidInputError(f"shares {shares} must be one per sampler, >= 0, summing to 1")
        self.samplers, self.shares, self.batch_size, self.seed = samplers, shares, batch_size, seed
        self.caches = [sampler.cache for sampler in samplers]
        self.offsets = np.cumsum([0] + [len(c.tokens) for c in self.caches[:-1]]).tolist()

    def __call__(self, step: int, process_index: int = 0) -> dict:
        draws = self._draws(step, process_index)
        return collate_batches([gather(s.cache, d) for s, d in zip(self.samplers, draws, strict=True)])

    def index(self, step: int, process_index: int = 0) -> ClipIndex:
        return ClipIndex.cat(self._draws(step, process_index), self.offsets)

    def _draws(self, step: int, process_index: int) -> list[ClipIndex]:
        """Each sampler's clips of the step: how many, at the shares, then which."""
        rng = np.random.default_rng([self.seed, step, process_index])
        counts = rng.multinomial(self.batch_size, self.shares)
        return [sampler.draw(rng, n) for sampler, n in zip(self.samplers, counts, strict=True)]


def gather(cache: TokenCache, index: ClipIndex) -> dict:
    """The batch at `index` from a cache's (memory-mapped) arrays: tokens (B, T, S) long, anchor (B, S) long (the
    episodes' first frames), actions (B, T, k, A), no_action (B, T), state (B, T, D), done (B, T), reward (B, T)
    and task (B strings)."""
    B, T = index.rows.shape
    S = int(np.prod(cache.tokens.shape[1:]))  # the views side by side
    actions = np.where(index.valid[..., None], cache.actions[index.action_rows], 0.0)
    return {
        "tokens": torch.from_numpy(cache.tokens[index.rows].reshape(B, T, S).astype(np.int64)),
        "anchor": torch.from_numpy(cache.tokens[index.anchor_rows].reshape(B, S).astype(np.int64)),
        "actions": torch.from_numpy(actions.astype(np.float32)),
        "no_action": torch.from_numpy(index.no_action),
        "state": torch.from_numpy(np.asarray(cache.states[index.rows], dtype=np.float32)),
        "done": torch.from_numpy(np.asarray(cache.done[index.rows], dtype=np.float32)),
        "reward": torch.from_numpy(np.asarray(cache.rewards[index.rows], dtype=np.float32)),
        "task": index.tasks,
    }


def collate_batches(batches: list[dict]) -> dict:
    merged = {key: torch.cat([b[key] for b in batches]) for key in batches[0] if key != "task"}
    merged["task"] = [task for b in batches for task in b["task"]]
    return merged


class ResidentClips:
    """The batches of a ClipSampler or ClipMixture, sliced on `device` from the token caches held there whole: each
    step sends only the clips' row indices (a few KiB) to the device, never their tokens, and nothing waits on it.
    The same batches as the sampler's, so a run may move between the two and resume."""

    def __init__(self, sampler: ClipSampler | ClipMixture, device: str | torch.device):
        self.sampler, self.device = sampler, torch.device(device)
        caches = sampler.caches

        def resident(name: str, dtype: torch.dtype) -> torch.Tensor:
            arrays = [np.asarray(getattr(c, name)).reshape(len(c.tokens), -1) for c in caches]
            return torch.from_numpy(np.concatenate(arrays)).to(self.device, dtype)

        # int32 codes (uint16 has no gather on every device); a bench cache of 200k frames takes 0.4 GB.
        self.tokens = resident("tokens", torch.int32)
        self.actions = resident("actions", torch.float32)
        self.states = resident("states", torch.float32)
        self.done = resident("done", torch.float32).squeeze(-1)
        self.rewards = resident("rewards", torch.float32).squeeze(-1)

    @property
    def nbytes(self) -> int:
        arrays = (self.tokens, self.actions, self.states, self.done, self.rewards)
        return sum(t.numel() * t.element_size() for t in arrays)

    def __call__(self, step: int, process_index: int = 0) -> dict:
        index = self.sampler.index(step, process_index)
        B, T = index.rows.shape
        rows, action_rows, valid, no_action, anchor_rows = (
            torch.from_numpy(np.ascontiguousarray(a)).to(self.device, non_blocking=True)
            for a in (index.rows, index.action_rows, index.valid, index.no_action, index.anchor_rows)
        )
        actions = self.actions[action_rows] * valid[..., None]
        return {
            "tokens": self.tokens[rows].view(B, T, -1).long(),
            "anchor": self.tokens[anchor_rows].long(),
            "actions": actions,
            "no_action": no_action,
            "state": self.states[rows],
            "done": self.done[rows],
            "reward": self.rewards[rows],
            "task": index.tasks,
        }
