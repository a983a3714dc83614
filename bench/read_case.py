"""The floor: just reading a generated C3D take (ezc3d, and mocapskel's reader), in a fresh process.

    python -m bench.read_case --frames 60000 --seed 1 --noise 1 --soft-tissue 2 --gaps 4

The take is generated as bench.fit_case generates it (same arguments, so the
same file), written to a temporary C3D, and read: ``ezc3d.c3d`` alone (the
floor) and :func:`~mocapskel.io.markers.read_markers`, each best of 3.
"""
from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

from bench.common import peak_rss_mb
from mocapskel.io.markers import read_markers, write_markers
from mocapskel.synth.presets import Recipe, make


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
    a = ap.parse_args()
    take = make(Recipe(kind="human", seed=a.seed, frames=a.frames, noise_mm=a.noise, soft_tissue_mm=a.soft_tissue,
                       gaps_per_marker_per_minute=a.gaps, markers_per_segment=a.mps,
                       jumps=a.jumps, ghosts=a.ghosts, passive=a.passive))
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "take.c3d"
        write_markers(p, take.markers)
        del take
        import ezc3d

        raw, ours = [], []
        for _ in range(3):
            t = time.perf_counter()
            c = ezc3d.c3d(str(p), extract_forceplat_data=False)
            raw.append(time.perf_counter() - t)
            del c
            t = time.perf_counter()
            m = read_markers(p)
            ours.append(time.perf_counter() - t)
            del m
        m = read_markers(p)
    print(json.dumps({"read_s": min(raw), "read_markers_s": min(ours), "frames": m.n_frames, "peak_rss_mb": peak_rss_mb()}))


if __name__ == "__main__":
    main()
