"""Speed and memory of ``fit``: the read floor, long takes, and scaling in frames and markers.

    python -m bench.speed               # markdown to stdout
    python -m bench.speed --long-only   # only the 60,000-frame active take's row of "Long takes"

Every measurement runs in a fresh process (bench.fit_case / bench.read_case).
"""
from __future__ import annotations

import argparse
import statistics
import sys

from bench.common import run_isolated, table


def fit_args(frames: int, seed: int = 1, passive: bool = False) -> list[str]:
    """The generator's arguments of the speed takes (bench.fit_case and bench.read_case take the same).

    passive: a new label after every gap, 25 ghosts, 10 jumps, and 1 gap per marker per minute
    instead of 4 (at 4, the 60,000-frame take would have some 1,650 labels: a 1.9 GB C3D file)."""
    gaps = "1" if passive else "4"
    args = ["--frames", str(frames), "--seed", str(seed), "--noise", "1", "--soft-tissue", "2", "--gaps", gaps]
    return args + (["--passive", "--ghosts", "25", "--jumps", "10"] if passive else [])


def fit(frames: int, seed: int = 1, mps: int | None = None, repeats: int = 1, passive: bool = False) -> dict:
    args = fit_args(frames, seed, passive)
    if mps:
        args += ["--mps", str(mps)]
    runs = [run_isolated("fit_case", *args) for _ in range(repeats)]
    out = dict(runs[-1])
    out["total_s"] = statistics.median(r["total_s"] for r in runs)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--long-only", action="store_true",
                    help="only the 60,000-frame active take of the long takes' table (no scaling tables)")
    a = ap.parse_args()
    print("### Long takes (human ROM: 48 markers, 120 Hz, 1 mm noise, 2 mm soft tissue; active: 4 gaps per marker "
          "per minute; passive: a new label after every gap, 1 gap per marker per minute, 25 ghosts, 10 jumps)\n")
    print("'fit': `pipeline.fit` from the C3D file plus the BVH write, in a fresh process (median of 3; "
          "stage times of the last run). 'CLI': the whole `mocapskel fit take.c3d -o take.bvh --no-cache -q` "
          "command from the shell — interpreter, imports, read, stages, BVH (median of 5; peak RSS of the command). "
          "'ezc3d read': `ezc3d.c3d(path, extract_forceplat_data=False)` of the same file, the first read in a fresh "
          "process as a fit's is (median of 3 processes; a process's later reads are faster).\n")
    rows = []
    cases = ((60000, False),) if a.long_only else ((7200, False), (60000, False), (7200, True), (60000, True))
    for frames, passive in cases:
        # the fit and the floor (ezc3d's first read of the same file in a fresh process) alternately, so that
        # both see the same load of a shared machine; median of 3 each
        fits, reads = [], []
        for _ in range(3):
            fits.append(fit(frames, passive=passive))
            reads.append(run_isolated("read_case", *fit_args(frames, passive=passive))["read_s"])
        r = dict(fits[-1], total_s=statistics.median(f["total_s"] for f in fits))
        rd = {"read_s": statistics.median(reads)}
        cli = run_isolated("cli_case", *fit_args(frames, passive=passive), "--repeats", "5")
        st = r["seconds"]
        rows.append([f"{frames} ({frames / 7200:.3g} min)" + (", passive" if passive else ""),
                     round(r["total_s"], 2), round(cli["wall_s"], 2),
                     round(rd["read_s"], 2), round(r["total_s"] / max(rd["read_s"], 1e-9), 1),
                     round(cli["wall_s"] / max(rd["read_s"], 1e-9), 1), round(cli["peak_rss_mb"]),
                     " ".join(f"{k} {v:.2f}" for k, v in st.items()), round(r["joint_rms_mm"], 2), "yes" if r["topology_ok"] else "NO"])
        print(f"  {frames}: {rows[-1]}", file=sys.stderr)
    print(table(["frames", "fit (s)", "CLI (s)", "ezc3d read (s)", "fit / read", "CLI / read", "CLI peak RSS (MB)",
                 "seconds per stage", "joint rms (mm)", "topology right"], rows))
    if a.long_only:
        return
    print("\n### Scaling in frames (48 markers)\n")
    rows = []
    for frames in (1000, 3000, 10000, 30000, 60000):
        r = fit(frames)
        rows.append([frames, round(r["total_s"], 2), round(1e6 * r["total_s"] / frames, 1), round(r["peak_rss_mb"]),
                     round(r["seconds"].get("ik", 0), 2), round(r["seconds"].get("joints", 0), 2)])
        print(f"  frames {frames}: {rows[-1]}", file=sys.stderr)
    print(table(["frames", "fit (s)", "µs per frame", "peak RSS (MB)", "ik (s)", "joints (s)"], rows))
    print("\n### Scaling in markers (7200 frames; markers per segment 1 … 6)\n")
    rows = []
    for mps in (1, 2, 3, 4, 6):
        r = fit(7200, mps=mps)
        rows.append([r["markers"], round(r["total_s"], 2), round(r["peak_rss_mb"]),
                     " ".join(f"{k} {v:.2f}" for k, v in r["seconds"].items() if v > 0.05), round(r["joint_rms_mm"], 2)])
        print(f"  mps {mps}: {rows[-1]}", file=sys.stderr)
    print(table(["markers", "fit (s)", "peak RSS (MB)", "stages over 0.05 s", "joint rms (mm)"], rows))
    print("\nWith 3 markers per segment or more, time grows slowly with the markers (read, clean and segment "
          "about linearly, the pair distances of segment quadratically but on a few hundred frames). The 15- and "
          "30-marker takes are slower for another reason: their segments carry 1 and 2 markers, so their joints "
          "come from JMV and the sphere fits instead of SCoRE, and the whole-skeleton refinement runs from two "
          "starts; that cost follows the markers per segment, not their number.")


if __name__ == "__main__":
    main()
