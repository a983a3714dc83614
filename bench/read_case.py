"""The floor: one read of a generated C3D take in a fresh process — ezc3d alone, or mocapskel's reader.

    python -m bench.read_case --frames 60000 --seed 1 --noise 1 --soft-tissue 2 --gaps 4 [--reader mocapskel]

The take is generated as bench.fit_case generates it (same arguments, so the
same file; in another process) and read once: ``ezc3d.c3d(path,
extract_forceplat_data=False)`` (default) or
:func:`~mocapskel.io.markers.read_markers`. Once, because that is what a fit
pays: a process's first read of a long take is the slowest (later reads
reuse the memory the first one took from the system).
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench.common import REPO, peak_rss_mb
from mocapskel.io.markers import read_markers


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--frames", type=int, default=60000)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--noise", type=float, default=0.0)
    ap.add_argument("--soft-tissue", type=float, default=0.0)
    ap.add_argument("--gaps", type=float, default=0.0)
    ap.add_argument("--mps", type=int, default=None, help="markers per segment (human)")
    ap.add_argument("--jumps", type=int, default=0)
    ap.add_argument("--ghosts", type=int, default=0)
    ap.add_argument("--passive", action="store_true")
    ap.add_argument("--reader", choices=("ezc3d", "mocapskel"), default="ezc3d")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as d:
        gen = [x for x in sys.argv[1:] if x not in ("--json", "--reader", "ezc3d", "mocapskel")]
        subprocess.run([sys.executable, "-m", "bench.fit_case", *gen, "--write", d], check=True, cwd=REPO)
        p = Path(d) / "take.c3d"
        import ezc3d

        t = time.perf_counter()
        if a.reader == "ezc3d":
            c = ezc3d.c3d(str(p), extract_forceplat_data=False)
            frames = int(c["parameters"]["POINT"]["FRAMES"]["value"][0])
        else:
            m = read_markers(p)
            frames = m.n_frames
        secs = time.perf_counter() - t
    print(json.dumps({"read_s": secs, "reader": a.reader, "frames": frames, "peak_rss_mb": peak_rss_mb()}))


if __name__ == "__main__":
    main()
