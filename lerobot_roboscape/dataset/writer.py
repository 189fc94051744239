"""Writes episodes as a LeRobotDataset v3, atomically: built in a temporary directory beside the target and
moved into place only when complete, so a failure leaves no partial dataset behind."""

import json
import os
import shutil
import tempfile
from collections.abc import Callable, Iterable
from pathlib import Path

import av
import datasets
import numpy as np
from lerobot.datasets.lerobot_dataset import LeRobotDataset, LeRobotDatasetMetadata
from lerobot.utils.constants import ACTION, DONE, OBS_IMAGES, OBS_STATE, REWARD, SUCCESS
from tqdm import tqdm

from lerobot_roboscape.dataset.episode import Episode
from lerobot_roboscape.dataset.segmentation import SEGMENTATION_DIR, write_masks
from roboscape_core.errors import InvalidInputError, OutputExistsError

# Per-episode facts (task family, scene, split, optimal, ...) that LeRobot's episode table has no column for.
EPISODES_SIDECAR = "meta/roboscape_episodes.jsonl"
# A dataset's own folders: LeRobot's, and the masks beside them. Anything else under its root (a pipeline's record
# of the run that wrote it) is not the dataset: not hashed into caches' keys, not pushed.
DATASET_FOLDERS = ("meta", "data", "videos", SEGMENTATION_DIR)
# LeRobot appends each episode's video to its camera's file by re-muxing the whole file, so writing N episodes into
# one file costs O(N^2): at its 200 MB default the bench's 2,048 episodes (about 60 MB per camera) share one file.
# A few MB bound each append (about 130 of our 64 px episodes per file); benchmark_dataset_writing.py measures it.
VIDEO_FILE_MB = 4


def _quiet_encoders() -> None:
    # One progress bar per stage is ours; hide the per-episode bars of `datasets` and SVT-AV1's warnings. LeRobot
    # hands libav's log back to its own printer (at INFO) after encoding, so its muxer would narrate every video it
    # joins ("[mp4 @ 0x...] Starting second pass"): warnings and errors only.
    datasets.disable_progress_bars()
    os.environ.setdefault("SVT_LOG", "1")
    av.logging.set_libav_level(av.logging.WARNING)


def dataset_features(
    episode: Episode, state_names: list[str] | None = None, action_names: list[str] | None = None
) -> dict:
    """LeRobot feature spec matching `episode`'s cameras and widths."""
    features = {}
    for camera, frames in episode.images.items():
        features[f"{OBS_IMAGES}.{camera}"] = {
            "dtype": "video",
            "shape": tuple(frames.shape[1:]),
            "names": ["height", "width", "channels"],
        }
    features[OBS_STATE] = {"dtype": "float32", "shape": (episode.state.shape[1],), "names": state_names}
    features[ACTION] = {"dtype": "float32", "shape": (episode.action.shape[1],), "names": action_names}
    features[REWARD] = {"dtype": "float32", "shape": (1,), "names": None}
    features[DONE] = {"dtype": "bool", "shape": (1,), "names": None}
    features[SUCCESS] = {"dtype": "bool", "shape": (1,), "names": None}
    return features


def _describe(episode: Episode, k: int, root: Path) -> str:
    """Where an episode comes from, for error messages: its source file, or its scene and seed."""
    info = episode.info
    if "source_file" in info:
        return f"{info['source_file']} episode {info['source_episode_id']} (episode {k} for {root})"
    if "scene" in info:
        return f"{info.get('task_family')} in {info['scene']}, seed {info.get('seed')} (episode {k} for {root})"
    return f"episode {k} for {root}"


def check_features(episode: Episode, features: dict, where: str) -> None:
    """Every episode of a dataset has the cameras and widths of its first."""
    for key, feature in dataset_features(episode).items():
        if key not in features or tuple(features[key]["shape"]) != tuple(feature["shape"]):
            expected = tuple(features[key]["shape"]) if key in features else "no such feature"
            raise InvalidInputError(
                f"{where}: {key} has shape {tuple(feature['shape'])} per frame, the dataset's first episode {expected}"
            )


def check_target(root: Path, overwrite: bool) -> None:
    if root.exists():
        if not overwrite:
            raise OutputExistsError(f"Output directory {root} already exists; choose another or pass --overwrite")
        if not (root / "meta" / "info.json").exists():
            raise OutputExistsError(f"Refusing to overwrite {root}: it exists and is not a LeRobot dataset")


def write_dataset(
    episodes: Iterable[Episode],
    repo_id: str,
    root: str | Path,
    fps: int,
    *,
    state_names: list[str] | None = None,
    action_names: list[str] | None = None,
    robot_type: str | None = None,
    overwrite: bool = False,
    total: int | None = None,
    keep: Callable[[Episode], bool] = lambda episode: True,
    video_file_mb: float = VIDEO_FILE_MB,
) -> LeRobotDataset:
    """Write `episodes` (any iterable, consumed once) to `root` and return the dataset opened for reading.

    Episodes for which `keep(episode)` is False are dropped. Raises ValueError if none is kept. A camera's video
    file holds episodes up to `video_file_mb` MB, then the next file begins.
    """
    root = Path(root).resolve()
    check_target(root, overwrite)
    _quiet_encoders()
    root.parent.mkdir(parents=True, exist_ok=True)
    for stale in root.parent.glob(f".{root.name}.partial-*"):  # left by a killed writer; never a dataset
        shutil.rmtree(stale, ignore_errors=True)
    staging_parent = Path(tempfile.mkdtemp(prefix=f".{root.name}.partial-", dir=root.parent))
    staging = staging_parent / root.name
    try:
        dataset, records, features, segmented = None, [], None, None
        for k, episode in enumerate(tqdm(episodes, total=total, desc=f"writing {repo_id}", unit="episode")):
            where = _describe(episode, k, root)
            episode.validate(where)
            if not keep(episode):
                continue
            if dataset is None:
                features = dataset_features(episode, state_names, action_names)
                # Streaming: frames go straight to the video encoder instead of through a PNG file each; the videos
                # are the same bytes (checked on 6 demo episodes) and writing takes 30% less time.
                dataset = LeRobotDataset.create(
                    repo_id,
                    fps=fps,
                    root=staging,
                    robot_type=robot_type,
                    use_videos=True,
                    features=features,
                    streaming_encoding=True,
                    # LeRobot drops a frame when the encoder's queue stays full for 0.1 s (a live robot must not
                    # wait); a recorded episode can, and a dropped frame shifts every later one in the video. An
                    # unbounded queue holds one episode at most: finishing an episode waits for its encoder.
                    encoder_queue_maxsize=0,
                    video_files_size_in_mb=video_file_mb,
                )
            check_features(episode, features, where)
            if segmented is None:
                segmented = episode.masks is not None
            elif (episode.masks is not None) != segmented:
                raise InvalidInputError(
                    f"{where}: {'has no' if segmented else 'has'} segmentation masks, unlike the dataset's first "
                    "episode; every episode of a dataset has them or none does"
                )
            _add_episode(dataset, episode)
            if segmented:
                write_masks(staging, len(records), episode.masks)
            records.append(
                {"episode_index": len(records), "length": len(episode), "task": episode.task, **episode.info}
            )
        if dataset is None:
            raise InvalidInputError(f"No episode to write to {root} (none produced, or none kept)")
        dataset.finalize()
        if missing := missing_video_frames(LeRobotDatasetMetadata(repo_id, root=staging)):
            raise InvalidInputError(f"writing {root}: videos short of their episodes' frames: {'; '.join(missing)}")
        with open(staging / EPISODES_SIDECAR, "w") as f:
            for record in records:
                f.write(json.dumps(record) + "\n")
        if root.exists():
            shutil.rmtree(root)
        os.replace(staging, root)
    finally:
        shutil.rmtree(staging_parent, ignore_errors=True)
    return LeRobotDataset(repo_id, root=root)


def missing_video_frames(meta: LeRobotDatasetMetadata) -> list[str]:
    """Each video file holding fewer frames than its episodes' lengths add up to ("FILE: N frames, M expected
    (episodes A-B)"); empty when every frame is there. A frame missing from a file shifts every later episode in it.
    Reads the metadata and demuxes the videos, without loading the frames' table."""
    expected: dict[tuple[str, Path], list[int]] = {}  # (camera, file) -> [frames, first episode, last episode]
    for index in range(meta.total_episodes):
        length = meta.episodes[index]["length"]
        for key in meta.video_keys:
            entry = expected.setdefault((key, meta.get_video_file_path(index, key)), [0, index, index])
            entry[0] += length
            entry[2] = index
    missing = []
    for (_, path), (frames, first, last) in expected.items():
        with av.open(str(meta.root / path)) as container:
            found = sum(1 for packet in container.demux(video=0) if packet.size)
        if found != frames:
            missing.append(f"{path}: {found} frames, {frames} expected (episodes {first}-{last})")
    return missing


def _add_episode(dataset: LeRobotDataset, episode: Episode) -> None:
    for t in range(len(episode)):
        frame = {f"{OBS_IMAGES}.{camera}": frames[t] for camera, frames in episode.images.items()}
        frame[OBS_STATE] = episode.state[t].astype(np.float32)
        frame[ACTION] = episode.action[t].astype(np.float32)
        frame[REWARD] = np.array([episode.reward[t]], dtype=np.float32)
        frame[DONE] = np.array([episode.done[t]], dtype=bool)
        frame[SUCCESS] = np.array([episode.success[t]], dtype=bool)
        frame["task"] = episode.task
        dataset.add_frame(frame)
    dataset.save_episode()


def read_episode_info(root: str | Path) -> list[dict]:
    """The per-episode facts written beside a dataset (empty if the dataset has none)."""
    path = Path(root) / EPISODES_SIDECAR
    if not path.exists():
        return []
    with open(path) as f:
        return [json.loads(line) for line in f if line.strip()]
