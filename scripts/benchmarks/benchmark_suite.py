"""The test suite's wall time against a reference commit's, both in one run on this machine (issue 71's target: the
suite not slower than the reference's). CI machines differ by up to 2x for the same code (stop 80 and stop 81: 1,725 s
and 885 s), so a figure is only a comparison where both sides ran on one machine, one after the other.

The reference is checked out as a git worktree in a temporary folder and run with this environment; every process
the tests start imports that tree's packages (PYTHONPATH names the tree's roots, as the editable install names this
checkout's). Each side runs the README's test command (pytest-xdist's default workers).

    .venv/bin/python scripts/benchmarks/benchmark_suite.py --reference 07c1919 --tier fast
    .venv/bin/python scripts/benchmarks/benchmark_suite.py --reference ed0bca8 --tier readme  # (a reference before
    # the e2e tier runs its whole suite under -m 'not e2e')
"""

import argparse
import os
import re
import subprocess
import sys
import sysconfig
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
SUMMARY = re.compile(r"^=*\s*(?P<counts>(?:\d+ \w+|no tests ran)[^\n]*?) in [\d.]+s", re.MULTILINE)


def package_roots(tree: Path) -> list[str]:
    """The folders this environment's editable install puts on sys.path (its `_editable_impl_*.pth`), mapped from
    this checkout onto `tree`."""
    site = Path(sysconfig.get_paths()["purelib"])
    roots = [Path(pth.read_text().strip()) for pth in sorted(site.glob("_editable_impl_*.pth"))]
    return [str(tree / root.relative_to(REPO)) for root in roots if root.is_relative_to(REPO)]


def run_suite(tree: Path, tier: str, extra: list[str]) -> dict:
    """One run of the test command in `tree` (`extra`: more pytest arguments): its wall seconds, pytest's own count
    line, the tests that failed (pytest's `FAILED` lines) and its exit code."""
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", *extra]
    cmd += {"fast": ["-m", "not slow"], "readme": ["-m", "not e2e"], "all": []}[tier]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(package_roots(tree))}
    start = time.perf_counter()
    done = subprocess.run(cmd, cwd=tree, env=env, capture_output=True, text=True)
    seconds = time.perf_counter() - start
    lines = list(SUMMARY.finditer(done.stdout))
    counts = lines[-1]["counts"] if lines else "no summary: " + " ".join(done.stdout.strip().splitlines()[-1:])
    failed = [line for line in done.stdout.splitlines() if line.startswith(("FAILED", "ERROR"))]
    return {"seconds": seconds, "counts": counts, "failed": failed, "returncode": done.returncode}


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--reference", required=True, help="the commit to compare against")
    parser.add_argument(
        "--tier", choices=("all", "readme", "fast"), default="all", help="readme: -m 'not e2e'; fast: -m 'not slow'"
    )
    parser.add_argument("--head-first", action="store_true", help="run this checkout before the reference")
    args, extra = parser.parse_known_args()  # the rest goes to pytest (e.g. a test file, to try the script)
    with tempfile.TemporaryDirectory(prefix="suite_reference_") as tmp:
        reference = Path(tmp) / "reference"
        subprocess.run(
            ["git", "-C", str(REPO), "worktree", "add", "--detach", str(reference), args.reference], check=True
        )
        try:
            sides = [("reference " + args.reference, reference), ("this checkout", REPO)]
            results = {
                name: run_suite(tree, args.tier, extra) for name, tree in (sides[::-1] if args.head_first else sides)
            }
        finally:
            subprocess.run(["git", "-C", str(REPO), "worktree", "remove", "--force", str(reference)], check=True)
    print(f"\n{args.tier} tier, {os.cpu_count()} cores, one run each, in the order below")
    print(f"{'side':<28} {'wall s':>8}  pytest")
    for name, r in results.items():
        print(f"{name:<28} {r['seconds']:8.0f}  {r['counts']} (exit {r['returncode']})")
    for name, r in results.items():
        print("".join(f"{name}: {line}\n" for line in r["failed"]), end="")
    ref, head = (r["seconds"] for r in (results[sides[0][0]], results[sides[1][0]]))
    print(f"this checkout / reference: {head / ref:.2f}")


if __name__ == "__main__":
    main()
