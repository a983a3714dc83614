"""The floor: just reading a generated C3D take (ezc3d, through mocapskel's reader), in a fresh process."""
from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

from bench.common import peak_rss_mb
from mocapskel.io.markers import read_markers, write_markers
from mocapskel.synth.presets import active_rom, make


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--frames", type=int, default=60000)
    a = ap.parse_args()
    take = make(active_rom(seed=1, frames=a.frames))
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "take.c3d"
        write_markers(p, take.markers)
        del take
        import ezc3d

        t = time.perf_counter()
        c = ezc3d.c3d(str(p), extract_forceplat_data=False)
        raw = time.perf_counter() - t
        del c
        t = time.perf_counter()
        m = read_markers(p)
        ours = time.perf_counter() - t
    print(json.dumps({"read_s": raw, "read_markers_s": ours, "frames": m.n_frames, "peak_rss_mb": peak_rss_mb()}))


if __name__ == "__main__":
    main()
