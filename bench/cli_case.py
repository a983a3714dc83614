"""`mocapskel fit` as a user runs it: wall time and peak memory of the whole command, from the shell.

    python -m bench.cli_case --frames 7200 --seed 1 --noise 1 --soft-tissue 2 --gaps 4 --repeats 5

The take is generated first (bench.fit_case's generator, same arguments), then
``mocapskel fit take.c3d -o take.bvh --no-cache -q`` runs ``--repeats`` times,
each a fresh process (interpreter start, imports, read, every stage, BVH
written). Prints the median and minimum wall time and the peak RSS of the runs.

The command is ``python -m mocapskel`` with this checkout first on the path and
the take's folder as the working directory: the installed ``mocapskel`` script
imports whatever checkout was installed, which need not be the one measured.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench.common import REPO


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--repeats", type=int, default=5)
    a, rest = ap.parse_known_args()
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH", "")])))
    with tempfile.TemporaryDirectory() as d:
        subprocess.run([sys.executable, "-m", "bench.fit_case", *rest, "--write", d], check=True, cwd=REPO)
        take = Path(d) / "take.c3d"
        walls, peaks = [], []
        for _ in range(a.repeats):
            t = time.perf_counter()
            p = subprocess.Popen([sys.executable, "-m", "mocapskel", "fit", str(take), "-o", str(Path(d) / "out.bvh"),
                                  "--no-cache", "-q"], cwd=d, env=env)
            _, status, ru = os.wait4(p.pid, 0)
            walls.append(time.perf_counter() - t)
            peaks.append(ru.ru_maxrss / 1024.0)
            if status != 0:
                raise SystemExit(f"mocapskel fit failed (status {status})")
    print(json.dumps({"wall_s": statistics.median(walls), "wall_min_s": min(walls), "peak_rss_mb": max(peaks),
                      "repeats": a.repeats}))


if __name__ == "__main__":
    main()
