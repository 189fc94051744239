"""Dataset writing time against the number of episodes, with the writer's video file size and LeRobot's default.

    .venv/bin/python scripts/benchmarks/benchmark_dataset_writing.py --episodes 600

LeRobot appends each episode's video to its camera's current file by re-muxing that file, so the time to append
grows with the file. Prints, in one run, for our `VIDEO_FILE_MB` and for LeRobot's default (the reference): the
seconds per episode over each tenth of the run, the total, and the video files per camera. The episodes are real:
a few planner demonstrations (both cameras, masks) collected once and written over and over, so each video file
fills at the rate a collection fills it.
"""

import argparse
import itertools
import tempfile
import time
from pathlib import Path

from lerobot.datasets.utils import DEFAULT_VIDEO_FILE_SIZE_IN_MB

from lerobot_roboscape.dataset.writer import VIDEO_FILE_MB
from lerobot_roboscape.demos.collect import CollectConfig, make_jobs, write_task_dataset
from lerobot_roboscape.demos.rollout import run_jobs


def timed_write(episodes: list, n: int, root: Path, video_file_mb: float) -> dict:
    stamps = []

    def stream():
        for episode in itertools.islice(itertools.cycle(episodes), n):
            yield episode
            stamps.append(time.perf_counter())  # the writer asks for the next episode once this one is saved

    start = time.perf_counter()
    dataset = write_task_dataset(stream(), "local/bench_writing", root, total=n, video_file_mb=video_file_mb)
    total = time.perf_counter() - start
    gaps = [b - a for a, b in zip([start, *stamps], stamps, strict=False)]
    tenth = max(1, n // 10)
    files = len(list((root / "videos").glob(f"{dataset.meta.video_keys[0]}/*/*.mp4")))
    return {
        "total": total,
        "per_tenth": [sum(gaps[i : i + tenth]) / len(gaps[i : i + tenth]) for i in range(0, len(gaps), tenth)],
        "files": files,
        "video_kb": sum(p.stat().st_size for p in (root / "videos").rglob("*.mp4")) / n / 1024,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--episodes", type=int, default=600, help="episodes written per setting")
    parser.add_argument("--distinct", type=int, default=8, help="planner episodes collected and written in turn")
    args = parser.parse_args()
    jobs = make_jobs(
        CollectConfig(
            families=["push", "pick_place"], max_scenes=args.distinct // 2, episodes_per_scene=1, segmentation=True
        )
    )
    episodes = list(run_jobs(jobs, workers=2))
    frames = sum(len(e) for e in episodes) / len(episodes)
    print(f"{len(episodes)} planner episodes, {frames:.0f} frames each on average, written {args.episodes} times")
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, mb in (("ours", VIDEO_FILE_MB), ("LeRobot default", DEFAULT_VIDEO_FILE_SIZE_IN_MB)):
            results[name] = r = timed_write(episodes, args.episodes, Path(tmp) / name.replace(" ", "_"), mb)
            print(
                f"{name} ({mb} MB per video file): {r['total']:.1f} s, {r['files']} file(s) per camera, "
                f"{r['video_kb']:.0f} KB of video per episode (both cameras)"
            )
            print("  s per episode, by tenth of the run: " + " ".join(f"{s:.3f}" for s in r["per_tenth"]))
    ours, ref = results["ours"]["total"], results["LeRobot default"]["total"]
    print(f"writing {args.episodes} episodes: {ref:.1f} s -> {ours:.1f} s ({ref / ours:.2f}x)")


if __name__ == "__main__":
    main()
