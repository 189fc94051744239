"""Pre-tokenised datasets for world-model training.

A cache is a directory of memory-mapped arrays plus a manifest naming the dataset and tokenizer it came from:

    manifest.json   fingerprints of dataset and tokenizer, grid and vocabulary sizes
    tokens.npy      (N, n_cameras, h, w) uint16 codes of every frame of every episode
    actions.npy     (N, action_dim) float32
    states.npy      (N, state_dim) float32 `observation.state` (joint positions and the TCP pose)
    done.npy        (N,) float32 done labels (1 where the task is accomplished in that frame)
    rewards.npy     (N,) float32 rule-based reward of each frame (labels of the baseline reward models)
    episodes.json   per episode: start row, length, task and the roboscape facts (family, scene, split, optimal)

Its directory name is derived from both fingerprints, so a changed dataset or retrained tokenizer gets a new cache
instead of a stale one; opening a cache with fingerprints that do not match raises `TokenCacheMismatchError`.

`export_token_cache` writes a cache and its dataset's statistics of the actions and states into one compressed file
that travels (to a GPU machine without the datasets); `import_token_cache` makes a cache of it there, which trains
without its dataset (STATS_FILE holds what the trainer would read of it).
"""

import hashlib
import io
import json
import lzma
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.utils.constants import OBS_STATE, SUCCESS
from tqdm import tqdm

from lerobot_roboscape.dataset.reader import camera_names, episode_indices, image_size, read_episode
from lerobot_roboscape.dataset.writer import DATASET_FOLDERS
from lerobot_roboscape.io.weights import weights_digest
from lerobot_roboscape.tokenizer.modeling_tokenizer import VisualTokenizer
from roboscape_core.errors import InvalidInputError, require_finite

FORMAT_VERSION = 3  # 3: the robot's state beside the actions
ARRAYS = ("tokens", "actions", "states", "done", "rewards")
STATS_FILE = "stats.json"  # an imported cache's dataset statistics: {"action": {...}, "observation.state": {...}}
STATS_KEYS = ("action", "observation.state")


class TokenCacheMismatchError(InvalidInputError):
    pass


def tokenizer_fingerprint(tokenizer: VisualTokenizer) -> str:
    return weights_digest(tokenizer, tokenizer.config.__dict__)


def dataset_fingerprint(root: str | Path) -> str:
    """Hash of the dataset's metadata and tables, plus the names and sizes of its videos: its own folders only."""
    root = Path(root)
    digest = hashlib.sha256()
    files = (p for folder in DATASET_FOLDERS for p in (root / folder).rglob("*") if p.is_file())
    for path in sorted(files):
        rel = path.relative_to(root).as_posix()
        digest.update(rel.encode())
        if path.suffix in (".json", ".jsonl", ".parquet"):
            digest.update(path.read_bytes())
        else:
            digest.update(str(path.stat().st_size).encode())
    return digest.hexdigest()


@dataclass
class TokenCache:
    root: Path
    manifest: dict
    tokens: np.ndarray  # (N, n_cameras, h, w) uint16, memory-mapped
    actions: np.ndarray  # (N, action_dim) float32
    states: np.ndarray  # (N, state_dim) float32
    done: np.ndarray  # (N,) float32
    rewards: np.ndarray  # (N,) float32
    episodes: list[dict]

    @property
    def vocab_size(self) -> int:
        return self.manifest["vocab_size"]

    @property
    def cameras(self) -> list[str]:
        return self.manifest["cameras"]

    @property
    def tokens_per_side(self) -> int:
        return self.manifest["tokens_per_side"]

    @property
    def action_dim(self) -> int:
        return self.actions.shape[1]

    @property
    def state_dim(self) -> int:
        return self.states.shape[1]

    @property
    def done_column(self) -> str | None:
        """The dataset column its done labels came from (`next.success`, `next.done`), None where it had neither
        (caches written before this was recorded came from this project's datasets, labelled by success)."""
        return self.manifest.get("done_column", SUCCESS)

    @property
    def has_done_labels(self) -> bool:
        return self.done_column is not None


def open_token_cache(path: str | Path, dataset_fp: str | None = None, tokenizer_fp: str | None = None) -> TokenCache:
    """Open a cache read-only; fingerprints given must match the manifest's."""
    path = Path(path)
    manifest_path = path / "manifest.json"
    if not manifest_path.is_file():
        raise TokenCacheMismatchError(
            f"{path} is not a token cache (no manifest.json); build one with roboscape-train-wm"
        )
    manifest = json.loads(manifest_path.read_text())
    if manifest.get("format_version") != FORMAT_VERSION:
        raise TokenCacheMismatchError(
            f"token cache {path} has format {manifest.get('format_version')}, this version "
            f"reads {FORMAT_VERSION}; delete it to rebuild it"
        )
    for name, expected in (("dataset", dataset_fp), ("tokenizer", tokenizer_fp)):
        if expected is not None and manifest[f"{name}_fingerprint"] != expected:
            raise TokenCacheMismatchError(
                f"token cache {path} was built from a different {name} "
                f"({manifest[f'{name}_fingerprint'][:12]}, expected {expected[:12]}); delete it or omit --token_cache "
                "to build a matching one"
            )
    arrays = {name: np.load(path / f"{name}.npy", mmap_mode="r") for name in ARRAYS}
    episodes = json.loads((path / "episodes.json").read_text())
    n = manifest["num_frames"]
    for name, array in arrays.items():
        if len(array) != n:
            raise TokenCacheMismatchError(f"{path / f'{name}.npy'} has {len(array)} rows, manifest says {n}")
    _check_values(path, arrays, episodes, manifest["vocab_size"])
    return TokenCache(path, manifest, episodes=episodes, **arrays)


def _check_values(path: Path, arrays: dict[str, np.ndarray], episodes: list[dict], vocab_size: int) -> None:
    """Labels and actions finite, codes inside the vocabulary; a fault names the dataset episode and frame."""
    starts = np.array([row["start"] for row in episodes])

    def row_name(row: int) -> str:
        episode = episodes[int(np.searchsorted(starts, row, side="right")) - 1]
        return f"(episode {episode['episode_index']} frame {row - episode['start']})"

    for name in ("actions", "states", "done", "rewards"):
        require_finite(arrays[name], str(path / f"{name}.npy"), name, row_name)
    if len(arrays["tokens"]) and int(arrays["tokens"].max()) >= vocab_size:
        row = int(np.argmax(arrays["tokens"].reshape(len(arrays["tokens"]), -1).max(axis=1) >= vocab_size))
        raise TokenCacheMismatchError(
            f"{path / 'tokens.npy'} {row_name(row)}: a code is outside the vocabulary of "
            f"{vocab_size}; delete the cache to rebuild it"
        )


def build_token_cache(
    dataset: LeRobotDataset,
    tokenizer: VisualTokenizer,
    path: str | Path,
    batch_size: int = 256,
    device: str | torch.device = "cpu",
) -> TokenCache:
    """Tokenize every frame of every episode of `dataset` into a cache at `path` (written atomically)."""
    path = Path(path)
    size = image_size(dataset)
    if size != tokenizer.config.image_size:
        raise TokenCacheMismatchError(
            f"dataset {dataset.root} has {size}x{size} images but the tokenizer expects {tokenizer.config.image_size}"
        )
    cameras, episodes = camera_names(dataset), episode_indices(dataset)
    side, n = tokenizer.config.tokens_per_side, dataset.num_frames
    path.parent.mkdir(parents=True, exist_ok=True)
    for stale in path.parent.glob(f".{path.name}.*"):  # left by a killed build; never opened as a cache
        shutil.rmtree(stale, ignore_errors=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", dir=path.parent))
    try:
        tokens = np.lib.format.open_memmap(tmp / "tokens.npy", "w+", np.uint16, (n, len(cameras), side, side))
        action_dim = dataset.meta.features["action"]["shape"][0]
        actions = np.lib.format.open_memmap(tmp / "actions.npy", "w+", np.float32, (n, action_dim))
        state = dataset.meta.features.get(OBS_STATE)  # a dataset may have none: the state channel is then off
        state_dim = state["shape"][0] if state else 0
        states = np.lib.format.open_memmap(tmp / "states.npy", "w+", np.float32, (n, state_dim))
        done = np.lib.format.open_memmap(tmp / "done.npy", "w+", np.float32, (n,))
        rewards = np.lib.format.open_memmap(tmp / "rewards.npy", "w+", np.float32, (n,))
        tokenizer = tokenizer.to(device).eval()
        rows, row, done_columns = [], 0, set()
        for index in tqdm(episodes, desc="tokenizing", unit="episode", leave=False):
            episode = read_episode(dataset, index)
            done_columns.add(episode.done_column)
            length = len(episode.action)
            for c, camera in enumerate(cameras):
                tokens[row : row + length, c] = encode_frames(tokenizer, episode.images[camera], batch_size)
            actions[row : row + length] = episode.action
            states[row : row + length] = episode.state
            done[row : row + length] = episode.done_label
            rewards[row : row + length] = episode.reward_label
            rows.append({**episode.info, "episode_index": index, "start": row, "length": length, "task": episode.task})
            row += length
        for array in (tokens, actions, states, done, rewards):
            array.flush()
        manifest = {
            "format_version": FORMAT_VERSION,
            "dataset_root": str(dataset.root),
            "dataset_fingerprint": dataset_fingerprint(dataset.root),
            "tokenizer_fingerprint": tokenizer_fingerprint(tokenizer),
            "cameras": cameras,
            "tokens_per_side": side,
            "vocab_size": tokenizer.config.codebook_size,
            "num_frames": n,
            "done_column": done_columns.pop() if len(done_columns) == 1 else None,
        }
        (tmp / "episodes.json").write_text(json.dumps(rows))
        (tmp / "manifest.json").write_text(json.dumps(manifest, indent=2))
        os.replace(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return open_token_cache(path)


@torch.no_grad()
def encode_frames(tokenizer: VisualTokenizer, images: np.ndarray, batch_size: int = 256) -> np.ndarray:
    """(T, H, W, 3) uint8 frames of one camera -> (T, h, w) uint16 codes, in batches on the tokenizer's device."""
    device = next(tokenizer.parameters()).device
    frames = torch.from_numpy(images).permute(0, 3, 1, 2)
    codes = [tokenizer.encode(frames[s : s + batch_size].to(device)) for s in range(0, len(frames), batch_size)]
    return torch.cat(codes).cpu().numpy().astype(np.uint16)


def episodes_token_cache(tokenizer: VisualTokenizer, episodes: list, cameras: list[str]) -> TokenCache:
    """An in-memory cache of episodes held in memory (each with `images` {camera: (T, H, W, 3)}, `action`, `state`,
    `done` and `task`, like `evaluation.success_rate.RecordedEpisode`), its rows laid out as `build_token_cache` lays a
    dataset's."""
    tokens, rows, start = [], [], 0
    for episode in episodes:
        tokens.append(np.stack([encode_frames(tokenizer, episode.images[camera]) for camera in cameras], axis=1))
        rows.append({"start": start, "length": len(episode.action), "task": episode.task})
        start += len(episode.action)
    done = np.concatenate([e.done for e in episodes]).astype(np.float32)
    return TokenCache(
        root=None,
        manifest={"cameras": cameras},
        tokens=np.concatenate(tokens),
        actions=np.concatenate([e.action for e in episodes]).astype(np.float32),
        states=np.concatenate([e.state for e in episodes]).astype(np.float32),
        done=done,
        rewards=np.zeros_like(done),
        episodes=rows,
    )


def load_or_build_token_cache(
    dataset: LeRobotDataset, tokenizer: VisualTokenizer, cache_dir: str | Path, device: str | torch.device = "cpu"
) -> TokenCache:
    """The cache of (`dataset`, `tokenizer`) under `cache_dir`, built on first use and reused afterwards."""
    dataset_fp, tokenizer_fp = dataset_fingerprint(dataset.root), tokenizer_fingerprint(tokenizer)
    path = Path(cache_dir) / f"v{FORMAT_VERSION}-{dataset_fp[:16]}-{tokenizer_fp[:16]}"
    if (path / "manifest.json").is_file():
        return open_token_cache(path, dataset_fp, tokenizer_fp)
    return build_token_cache(dataset, tokenizer, path, device=device)


def export_token_cache(cache: TokenCache, path: str | Path, stats: dict) -> int:
    """The cache and its dataset's statistics (dataset.meta.stats of STATS_KEYS) in one xz file; returns its
    bytes. A code is stored as 0 where it repeats the previous control step's at its place in the episode, else as
    code + 1: between two control steps most of a frame is unchanged, so the zeros compress away."""
    tokens = np.asarray(cache.tokens).reshape(len(cache.tokens), -1)
    repeats = np.zeros(tokens.shape, dtype=bool)
    repeats[1:] = tokens[1:] == tokens[:-1]
    repeats[[row["start"] for row in cache.episodes]] = False  # an episode's first frame is stored whole
    coded = np.where(repeats, 0, tokens.astype(np.uint32) + 1).astype(np.uint16)
    header = {
        "manifest": cache.manifest,
        "episodes": cache.episodes,
        "token_shape": list(cache.tokens.shape),
        "stats": {key: {k: np.asarray(v).tolist() for k, v in stats[key].items()} for key in STATS_KEYS},
    }
    buffer = io.BytesIO()
    np.savez(
        buffer,
        header=np.frombuffer(json.dumps(header).encode(), dtype=np.uint8),
        tokens=coded,
        actions=np.asarray(cache.actions),
        states=np.asarray(cache.states),
        done=np.asarray(cache.done),
        rewards=np.asarray(cache.rewards),
    )
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    with lzma.open(tmp, "wb", preset=6) as f:
        f.write(buffer.getvalue())
    os.replace(tmp, path)
    return path.stat().st_size


def import_token_cache(path: str | Path, cache_dir: str | Path) -> Path:
    """A cache under `cache_dir`, named as load_or_build_token_cache names it, from an exported file; its dataset's
    statistics beside it (STATS_FILE). Returns its directory."""
    path = Path(path)
    try:
        with lzma.open(path) as f:
            arrays = dict(np.load(io.BytesIO(f.read())))
        header = json.loads(arrays.pop("header").tobytes())
    except (lzma.LZMAError, OSError, ValueError, KeyError) as error:
        raise InvalidInputError(f"{path}: not a token cache exported by export_token_cache ({error})") from error
    if "stats" not in header:
        raise InvalidInputError(
            f"{path}: exported before token caches held the robot's state; export it again from its dataset"
        )
    manifest = header["manifest"]
    name = f"v{FORMAT_VERSION}-{manifest['dataset_fingerprint'][:16]}-{manifest['tokenizer_fingerprint'][:16]}"
    target = Path(cache_dir) / name
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{name}.", dir=target.parent))
    coded = arrays.pop("tokens")
    # A repeat takes the code of the last row at or above it that stored one (rows that store none: 0).
    source = np.maximum.accumulate(np.where(coded != 0, np.arange(len(coded))[:, None], 0), axis=0)
    tokens = np.take_along_axis(coded, source, axis=0).astype(np.int32) - 1
    np.save(tmp / "tokens.npy", tokens.astype(np.uint16).reshape(header["token_shape"]))
    for name_, array in arrays.items():
        np.save(tmp / f"{name_}.npy", array)
    (tmp / "episodes.json").write_text(json.dumps(header["episodes"]))
    (tmp / "manifest.json").write_text(json.dumps(manifest, indent=2))
    (tmp / STATS_FILE).write_text(json.dumps(header["stats"]))
    shutil.rmtree(target, ignore_errors=True)
    os.replace(tmp, target)
    return target
