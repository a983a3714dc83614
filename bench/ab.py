"""The working tree's code against another commit's, on the same takes in the same hour.

    python -m bench.ab                          # this tree against HEAD, on the slowest real takes
    python -m bench.ab --base 480f937 --repeat 3 TAKE.c3d ...

A machine shared with others runs the same fit 10-25 % faster or slower from one
day to the next, so a time from another day says little about a change. This runs
``mocapskel fit TAKE -o x.bvh --no-cache -q`` with each version alternately, in
fresh processes started outside the repository (``python -m`` puts the current
directory first on the path: from inside the repository it would run the
repository's code whatever ``PYTHONPATH`` says), and prints per take the median
wall time of each, their ratio and whether the two BVH files are identical.

The base commit is checked out into a temporary git worktree, removed after. The
default takes are the real takes of ``../shared/realdata/`` over 10 s in
BENCHMARKS.md's "Real takes" on 2026-12-03; name others on the command line.
"""
from __future__ import annotations

import argparse
import filecmp
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench.common import REPO, compile_package, table

REALDATA = REPO.parent / "shared" / "realdata"
SLOWEST = ("cmu/135_02.c3d", "joint-localization/fullbody_44Markers_clean_120fps.c3d",
           "hdm05/HDM_mm_01-02_03_120.c3d", "biobuddy/functional_trials/right_hip.c3d",
           "biobuddy/lower_limb_calibration/functional_trunk.c3d", "cmu/85_02.c3d")


def fit_time(code: Path, take: Path, out: Path, cwd: Path) -> float:
    """Wall time of one ``mocapskel fit`` with the package at ``code`` (a checkout's root)."""
    env = dict(os.environ, PYTHONPATH=str(code))
    cmd = [sys.executable, "-m", "mocapskel", "fit", str(take), "-o", str(out), "--no-cache", "-q"]
    t = time.perf_counter()
    done = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t
    if done.returncode != 0:
        raise SystemExit(f"{take.name}: fit failed with {code} (exit {done.returncode}): {done.stderr.strip()[-300:]}")
    return wall


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("takes", nargs="*", help="take files (default: the slowest real takes)")
    ap.add_argument("--base", default="HEAD", help="the commit to compare with (default HEAD)")
    ap.add_argument("--repeat", type=int, default=1, help="runs of each version per take (median)")
    a = ap.parse_args()
    takes = [Path(t).resolve() for t in a.takes] or [REALDATA / t for t in SLOWEST]
    missing = [str(t) for t in takes if not t.exists()]
    if missing:
        raise SystemExit(f"not found: {', '.join(missing)}")
    rows = []
    with tempfile.TemporaryDirectory(prefix="mocapskel-ab-") as tmp:
        tmp = Path(tmp)
        base = tmp / "base"
        subprocess.run(["git", "-C", str(REPO), "worktree", "add", "--detach", "-q", str(base), a.base], check=True)
        try:
            compile_package(base)  # as for this tree
            for take in takes:
                times = {"base": [], "new": []}
                for _ in range(max(1, a.repeat)):
                    for which, code in (("base", base), ("new", REPO)):  # alternately: the same load on both
                        times[which].append(fit_time(code, take, tmp / f"{which}.bvh", tmp))
                same = filecmp.cmp(tmp / "base.bvh", tmp / "new.bvh", shallow=False)
                b, n = statistics.median(times["base"]), statistics.median(times["new"])
                rows.append([take.name, round(b, 1), round(n, 1), round(n / b, 2), "yes" if same else "no"])
                print(f"  {rows[-1]}", file=sys.stderr)
        finally:
            subprocess.run(["git", "-C", str(REPO), "worktree", "remove", "--force", str(base)], check=False)
    print(f"`python -m bench.ab --base {a.base}` ({max(1, a.repeat)} run(s) of each, alternately)\n")
    print(table(["take", f"{a.base} (s)", "working tree (s)", "ratio", "same BVH"], rows))


if __name__ == "__main__":
    main()
