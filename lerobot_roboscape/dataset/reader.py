"""Reads the collected LeRobot datasets back for model training: whole episodes in order, or random frames."""

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa
import torch
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.datasets.video_utils import decode_video_frames
from lerobot.utils.constants import ACTION, DONE, OBS_IMAGES, OBS_STATE, REWARD, SUCCESS

from lerobot_roboscape.dataset.segmentation import read_masks
from lerobot_roboscape.dataset.writer import read_episode_info
from roboscape_core.errors import InvalidInputError, require_finite


class DatasetError(InvalidInputError):
    pass


# The columns a frame's done label is read from, the first a dataset has: `next.success` (this project's collection),
# else `next.done` (lerobot-record's episode end). Only the done head needs one.
DONE_LABEL_COLUMNS = (SUCCESS, DONE)


def open_dataset(repo_id: str, root: str | Path | None = None, episodes: list[int] | None = None) -> LeRobotDataset:
    """A LeRobotDataset with at least one camera and one episode, or a `DatasetError` naming what is missing."""
    if root is not None:
        info_path = Path(root) / "meta" / "info.json"
        if not info_path.is_file():
            raise DatasetError(
                f"no LeRobot dataset at {root} (meta/info.json is missing); collect one with roboscape-collect"
            )
        # Checked before LeRobotDataset, which would otherwise look for the missing files on the Hub.
        if json.loads(info_path.read_text()).get("total_episodes", 0) == 0:
            raise DatasetError(f"dataset {root} has no episodes ({info_path} says total_episodes is 0)")
    dataset = LeRobotDataset(repo_id, root=root, episodes=episodes)
    where = root or repo_id
    if dataset.meta.total_episodes == 0 or dataset.num_frames == 0:
        raise DatasetError(f"dataset {where} has no episodes")
    if not dataset.meta.camera_keys:
        raise DatasetError(f"dataset {where} has no camera features ({OBS_IMAGES}.<camera>)")
    if ACTION not in dataset.features:
        raise DatasetError(f"dataset {where} has no '{ACTION}' feature")
    check_finite(dataset)
    return dataset


def check_finite(dataset: LeRobotDataset) -> None:
    """Refuse a dataset whose states, actions or rewards hold NaN or inf, naming the episode, frame and key."""
    table = dataset.hf_dataset.data  # the Arrow table, without LeRobot's per-row conversion to tensors
    episode, frame = table.column("episode_index").to_numpy(), table.column("frame_index").to_numpy()
    for key in (OBS_STATE, ACTION, REWARD):
        if key not in table.column_names:
            continue
        column = table.column(key).combine_chunks()
        if pa.types.is_fixed_size_list(column.type):
            values = column.flatten().to_numpy(zero_copy_only=False).reshape(len(column), -1)
        else:
            values = column.to_numpy(zero_copy_only=False)
        require_finite(values, f"dataset {dataset.root}", key, lambda row: f"episode {episode[row]} frame {frame[row]}")


def camera_name(key: str) -> str:
    """A camera's name from its dataset key: `observation.images.<name>` (LeRobot's convention for several cameras),
    or a lone camera's key after `observation.` (`observation.image`, LeRobot's PushT layout: "image")."""
    return key.removeprefix(f"{OBS_IMAGES}.") if key.startswith(f"{OBS_IMAGES}.") else key.removeprefix("observation.")


def camera_names(dataset: LeRobotDataset) -> list[str]:
    return [camera_name(key) for key in dataset.meta.camera_keys]


@dataclass
class DatasetLayout:
    """What a LeRobot dataset's meta/info.json says of it: its cameras (name -> the dataset's key), their side, the
    widths of its actions and states (0: none) and its fps."""

    cameras: dict[str, str]
    image_size: int
    action_dim: int
    state_dim: int
    fps: int


def read_layout(root: str | Path) -> DatasetLayout:
    """The layout of the dataset at `root`, from its meta/info.json alone (no frame is read)."""
    path = Path(root) / "meta" / "info.json"
    if not path.is_file():
        raise DatasetError(f"no LeRobot dataset at {root} (meta/info.json is missing)")
    info = json.loads(path.read_text())
    features = info["features"]
    cameras = {camera_name(k): k for k, f in features.items() if f.get("dtype") in ("video", "image")}
    if not cameras:
        raise DatasetError(f"dataset {root} has no camera features (dtype video or image in {path})")
    if ACTION not in features:
        raise DatasetError(f"dataset {root} has no '{ACTION}' feature ({path})")
    sides = {tuple(features[k]["shape"][:2]) for k in cameras.values()}
    if len(sides) != 1 or len(side := sides.pop()) != 2 or side[0] != side[1]:
        raise DatasetError(f"dataset {root} cameras must be square and of one size, got {sorted(sides)} ({path})")
    state = features.get(OBS_STATE)
    return DatasetLayout(
        cameras, side[0], features[ACTION]["shape"][0], state["shape"][0] if state else 0, int(info["fps"])
    )


def image_size(dataset: LeRobotDataset) -> int:
    """Side of the square camera images; a `DatasetError` when views are not square or differ."""
    shapes = {tuple(dataset.features[key]["shape"]) for key in dataset.meta.camera_keys}
    sides = {s[0] for s in shapes} | {s[1] for s in shapes}
    if len(sides) != 1:
        raise DatasetError(
            f"dataset {dataset.root} cameras must be square and of one size, got shapes {sorted(shapes)}"
        )
    return sides.pop()


@dataclass
class EpisodeData:
    index: int
    task: str
    images: dict[str, np.ndarray]  # camera -> (T, H, W, 3) uint8
    action: np.ndarray  # (T, action_dim) float32
    state: np.ndarray  # (T, state_dim) float32: `observation.state` of frame t ((T, 0) when the dataset has none)
    done_label: np.ndarray  # (T,) float32: 1 where the task is accomplished in frame t (0 when unlabelled)
    reward_label: np.ndarray  # (T,) float32: the rule-based reward of frame t (0 when the dataset has none)
    info: dict  # the roboscape per-episode facts (family, scene, split, optimal, ...) when recorded
    done_column: str | None = SUCCESS  # the column of DONE_LABEL_COLUMNS its done labels came from (None: none)

    @property
    def has_done_labels(self) -> bool:
        return self.done_column is not None


def episode_indices(dataset: LeRobotDataset) -> list[int]:
    return list(dataset.episodes) if dataset.episodes is not None else list(range(dataset.meta.total_episodes))


def read_episode(dataset: LeRobotDataset, episode_index: int) -> EpisodeData:
    """All frames of one episode, decoded in one pass per camera (far faster than frame-by-frame access)."""
    meta = dataset.meta.episodes[episode_index]
    start, stop = meta["dataset_from_index"], meta["dataset_to_index"]
    rows = dataset.hf_dataset.select(range(*_local_range(dataset, start, stop)))
    images = _decode_cameras(dataset, episode_index, [float(t) for t in rows["timestamp"]])
    # `next.success` at t is the outcome of action t, i.e. the state of frame t + 1.
    flags = next((column for column in DONE_LABEL_COLUMNS if column in rows.column_names), None)
    length = len(rows)
    outcome = np.zeros(length, np.float32) if flags is None else np.asarray(rows[flags], np.float32).reshape(-1)
    done_label = np.concatenate([[0.0], outcome[:-1]]).astype(np.float32)
    if REWARD in rows.column_names:  # like success, `next.reward` at t scores frame t + 1
        rewards = np.asarray(rows[REWARD], dtype=np.float32).reshape(-1)
        reward_label = np.concatenate([rewards[:1], rewards[:-1]]).astype(np.float32)
    else:
        reward_label = np.zeros(len(outcome), dtype=np.float32)
    info = episode_facts(dataset, episode_index)
    return EpisodeData(
        index=episode_index,
        task=meta["tasks"][0],
        images=images,
        action=np.asarray(rows[ACTION], dtype=np.float32),
        state=np.asarray(rows[OBS_STATE], np.float32) if OBS_STATE in rows.column_names else np.zeros((length, 0)),
        done_label=done_label,
        reward_label=reward_label,
        info=info,
        done_column=flags,
    )


def read_frames(dataset: LeRobotDataset, episode_index: int, frames: list[int]) -> dict[str, np.ndarray]:
    """Selected frames of one episode (negative indices count from its end): camera -> (k, H, W, 3) uint8."""
    length = dataset.meta.episodes[episode_index]["length"]
    return _decode_cameras(dataset, episode_index, [(f % length) / dataset.fps for f in frames])


def read_states(dataset: LeRobotDataset, episode_index: int, frames: list[int]) -> np.ndarray:
    """`observation.state` (k, state_dim) of selected frames of one episode (negative indices count from its end),
    without decoding its videos; (k, 0) when the dataset has no states."""
    if OBS_STATE not in dataset.features:
        return np.zeros((len(frames), 0), np.float32)
    meta = dataset.meta.episodes[episode_index]
    rows = dataset.hf_dataset.select(
        range(*_local_range(dataset, meta["dataset_from_index"], meta["dataset_to_index"]))
    )
    states = np.asarray(rows.select_columns([OBS_STATE])[OBS_STATE], dtype=np.float32)
    return states[[f % len(states) for f in frames]]


def _decode_cameras(dataset: LeRobotDataset, episode_index: int, timestamps: list[float]) -> dict[str, np.ndarray]:
    """Frames of one episode at `timestamps` (seconds from its start), one decoding pass per camera."""
    meta = dataset.meta.episodes[episode_index]
    images = {}
    for key in dataset.meta.camera_keys:
        path = dataset.root / dataset.meta.get_video_file_path(episode_index, key)
        offset = meta[f"videos/{key}/from_timestamp"]
        decoded = decode_video_frames(path, [offset + t for t in timestamps], dataset.tolerance_s, return_uint8=True)
        images[camera_name(key)] = decoded.permute(0, 2, 3, 1).numpy()
    return images


def episode_facts(dataset: LeRobotDataset, episode_index: int) -> dict:
    """The roboscape facts of an episode (family, scene, split, optimal, success), {} when not recorded."""
    return _sidecar(dataset).get(episode_index, {})


def successful_episodes(dataset: LeRobotDataset) -> list[int]:
    """Indices of the episodes that accomplished their task: their recorded `success` fact, or where none is
    recorded, the `next.success` flag of their last frame."""
    successful = []
    for index in episode_indices(dataset):
        succeeded = episode_facts(dataset, index).get("success")
        if succeeded is None:
            if SUCCESS not in dataset.features:
                raise DatasetError(
                    f"dataset {dataset.root} records no success of episode {index} (no roboscape "
                    f"facts, no '{SUCCESS}' feature)"
                )
            meta = dataset.meta.episodes[index]
            _, stop = _local_range(dataset, meta["dataset_from_index"], meta["dataset_to_index"])
            succeeded = bool(np.asarray(dataset.hf_dataset[stop - 1][SUCCESS]).any())
        if succeeded:
            successful.append(index)
    return successful


def demonstrations_per_scene(
    dataset: LeRobotDataset, per_scene: int | None, scenes: list[str] | None = None
) -> list[int]:
    """The first `per_scene` successful episodes of each (task family, scene), in index order (None: all of them),
    of the `scenes` given (None: every scene): the demonstrations an SFT run of that data imitates."""
    kept, counts = [], {}
    for index in successful_episodes(dataset):
        facts = episode_facts(dataset, index)
        key = (facts.get("task_family"), facts.get("scene"))
        if scenes is not None and key[1] not in scenes:
            continue
        if per_scene is None or counts.get(key, 0) < per_scene:
            counts[key] = counts.get(key, 0) + 1
            kept.append(index)
    return kept


def _local_range(dataset: LeRobotDataset, start: int, stop: int) -> tuple[int, int]:
    # With an episode selection, hf_dataset holds only the selected rows; find this episode's rows among them.
    if dataset.episodes is None:
        return start, stop
    index = np.asarray(dataset.hf_dataset["index"])
    first = int(np.searchsorted(index, start))
    return first, first + (stop - start)


def _sidecar(dataset: LeRobotDataset) -> dict[int, dict]:
    if not hasattr(dataset, "_roboscape_info"):
        try:
            rows = read_episode_info(dataset.root)
        except FileNotFoundError:
            rows = []
        dataset._roboscape_info = {row["episode_index"]: row for row in rows}
    return dataset._roboscape_info


class CameraFrames(torch.utils.data.Dataset):
    """Random access to single frames of every camera, decoded from the videos on each access: (n_cameras, 3, H, W)
    float in [0, 1], with (n_cameras, H, W) uint8 labels (dataset/segmentation.py) when `masks`. For datasets too
    large for `FrameBank`."""

    def __init__(self, dataset: LeRobotDataset, masks: bool = False):
        self.dataset, self.masks = dataset, masks
        self.keys = dataset.meta.camera_keys

    def __len__(self) -> int:
        return self.dataset.num_frames

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        item = self.dataset[i]
        out = {"images": torch.stack([item[key] for key in self.keys])}
        if self.masks:
            episode, frame = int(item["episode_index"]), int(item["frame_index"])
            length = self.dataset.meta.episodes[episode]["length"]
            labels = read_masks(self.dataset.root, episode, camera_names(self.dataset), length, mmap=True)
            out["masks"] = torch.from_numpy(np.stack([m[frame] for m in labels.values()]))
        return out


@dataclass
class FrameBank:
    """Every frame of some episodes, decoded once and kept in memory (a video decode per random frame would cost
    more than a tokenizer step on a CPU).

    images: (N, n_cameras, H, W, 3) uint8; masks: (N, n_cameras, H, W) uint8 labels, or None;
    episode_index / frame_index: (N,) where each frame comes from.
    """

    images: torch.Tensor
    masks: torch.Tensor | None
    episode_index: np.ndarray
    frame_index: np.ndarray

    def __len__(self) -> int:
        return len(self.images)

    @staticmethod
    def nbytes(dataset: LeRobotDataset) -> int:
        """Memory the decoded frames of `dataset` take."""
        side = image_size(dataset)
        return dataset.num_frames * len(dataset.meta.camera_keys) * side * side * 3

    @classmethod
    def load(cls, dataset: LeRobotDataset, masks: bool = False, stride: int = 1) -> "FrameBank":
        """Every `stride`-th frame of each episode of `dataset`, with their labels when `masks`."""
        cameras = camera_names(dataset)
        images, labels, episodes, frames = [], [], [], []
        for index in episode_indices(dataset):
            episode = read_episode(dataset, index)
            keep = np.arange(0, len(episode.action), stride)
            images.append(np.stack([episode.images[c][keep] for c in cameras], 1))
            if masks:
                recorded = read_masks(dataset.root, index, cameras, len(episode.action))
                labels.append(np.stack([recorded[c][keep] for c in cameras], 1))
            episodes.append(np.full(len(keep), index))
            frames.append(keep)
        return cls(
            torch.from_numpy(np.concatenate(images)),
            torch.from_numpy(np.concatenate(labels)) if masks else None,
            np.concatenate(episodes),
            np.concatenate(frames),
        )


def family_horizons(dataset: LeRobotDataset) -> dict[str | None, int]:
    """The fixed RL horizon of each task family: its longest successful episode in the dataset, so that every
    demonstrated way of doing the task fits (all its episodes when none succeeded). Key None: over all families."""
    successful = set(successful_episodes(dataset))
    lengths: dict[str | None, list[tuple[bool, int]]] = {}
    for index in episode_indices(dataset):
        entry = (index in successful, int(dataset.meta.episodes[index]["length"]))
        for key in (episode_facts(dataset, index).get("task_family"), None):
            lengths.setdefault(key, []).append(entry)
    return {
        key: max(n for ok, n in entries if ok or not any(ok for ok, _ in entries)) for key, entries in lengths.items()
    }


def action_range(dataset: LeRobotDataset) -> tuple[np.ndarray, np.ndarray]:
    """Per-dimension (low, high) of the dataset's actions, from its statistics."""
    stats = dataset.meta.stats[ACTION]
    return np.asarray(stats["min"], dtype=np.float32), np.asarray(stats["max"], dtype=np.float32)
