"""Collection and conversion throughput, side by side with ManiSkill's own motion-planning runner.

    .venv/bin/python scripts/benchmarks/benchmark_collection.py --episodes 8 --image-size 64

Prints, in one run:
- roboscape-collect: episodes/min and frames/s (both cameras rendered and stored), pick&place, `--workers`.
- roboscape-convert: frames/s from a ManiSkill .h5 (written by RecordEpisode) to a LeRobotDataset.
- reference: `mani_skill.examples.motionplanning.panda.run` on PickCube-v1 recording RGB (one camera), with the
  same number of processes. It needs mplib 0.1.1, which crashes under NumPy 2, so it runs in a throwaway
  virtual environment with NumPy < 2 (made with uv from its cache; skipped with a message if that fails).
"""

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import h5py

ROOT = Path(__file__).resolve().parents[2]


def bench_collect(tmp: Path, episodes: int, image_size: int, workers: int) -> dict:
    from lerobot_roboscape.demos.collect import CollectConfig, collect

    cfg = CollectConfig(
        root=str(tmp / "collected"),
        families=["pick_place"],
        max_scenes=episodes,
        episodes_per_scene=1,
        failed_fraction=0.0,
        suboptimal_fraction=0.0,
        image_size=image_size,
        workers=workers,
    )
    start = time.perf_counter()
    ds = collect(cfg)
    seconds = time.perf_counter() - start
    return {"episodes": ds.meta.total_episodes, "frames": ds.meta.total_frames, "seconds": seconds}


def bench_convert(tmp: Path, image_size: int) -> dict:
    from lerobot_roboscape.dataset.convert import ConvertConfig, convert
    from lerobot_roboscape.demos.record import record_maniskill_trajectories
    from lerobot_roboscape.tasks import SCENES

    h5 = record_maniskill_trajectories(tmp / "ms", "pick_place", SCENES[0].id, episodes=3, image_size=image_size)
    start = time.perf_counter()
    ds = convert(ConvertConfig(h5=str(h5), root=str(tmp / "converted")))
    return {"frames": ds.meta.total_frames, "seconds": time.perf_counter() - start}


def bench_maniskill_runner(tmp: Path, episodes: int, workers: int) -> dict | str:
    venv = tmp / "ms-numpy1"
    try:
        subprocess.run(["uv", "venv", "-q", "--python", sys.executable, str(venv)], check=True)
        subprocess.run(
            [
                "uv",
                "pip",
                "install",
                "-q",
                "--python",
                str(venv / "bin" / "python"),
                "mani-skill==3.0.1",
                "numpy<2",
                "torch==2.11.0",
                "setuptools<81",
                "opencv-python-headless",
            ],
            check=True,
        )
    except (subprocess.CalledProcessError, FileNotFoundError) as e:
        return f"skipped: could not build the NumPy<2 environment ({e})"
    record_dir = tmp / "ms_runner"
    cmd = [
        str(venv / "bin" / "python"),
        "-m",
        "mani_skill.examples.motionplanning.panda.run",
        "-e",
        "PickCube-v1",
        "-o",
        "rgb",
        "-n",
        str(episodes),
        "-b",
        "cpu",
        "--num-procs",
        str(workers),
        "--record-dir",
        str(record_dir),
    ]
    start = time.perf_counter()
    result = subprocess.run(cmd, capture_output=True, text=True)
    seconds = time.perf_counter() - start
    if result.returncode != 0:
        return f"failed (exit {result.returncode}): {result.stderr.strip().splitlines()[-1:]}"
    frames = 0
    for path in record_dir.rglob("*.h5"):
        with h5py.File(path) as f:
            frames += sum(f[k]["actions"].shape[0] for k in f if k.startswith("traj_"))
    return {"episodes": episodes, "frames": frames, "seconds": seconds}


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--episodes", type=int, default=8)
    parser.add_argument("--image-size", type=int, default=64)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--skip-reference", action="store_true")
    args = parser.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="roboscape-bench-"))
    try:
        results = {
            "collect": bench_collect(tmp, args.episodes, args.image_size, args.workers),
            "convert": bench_convert(tmp, args.image_size),
        }
        if not args.skip_reference:
            results["maniskill_motionplanning_runner"] = bench_maniskill_runner(tmp, args.episodes, args.workers)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)

    print(f"\nimage size {args.image_size}x{args.image_size}, {args.workers} workers, {args.episodes} episodes")
    print(f"{'what':52s} {'episodes/min':>12s} {'frames/s':>9s}")
    rows = [
        ("roboscape-collect pick_place (2 cameras, to LeRobot)", results["collect"]),
        ("roboscape-convert (ManiSkill .h5 -> LeRobot)", results["convert"]),
    ]
    if "maniskill_motionplanning_runner" in results:
        rows.append(("ManiSkill motionplanning runner PickCube (1 camera)", results["maniskill_motionplanning_runner"]))
    for name, r in rows:
        if isinstance(r, str):
            print(f"{name:52s} {r}")
            continue
        per_min = f"{60 * r['episodes'] / r['seconds']:.2f}" if "episodes" in r else "-"
        print(f"{name:52s} {per_min:>12s} {r['frames'] / r['seconds']:9.1f}")
    print(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
