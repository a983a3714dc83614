"""Batch throughput: the same takes fitted by 1 and by 2 local worker processes.

    python -m bench.batch                    # 20 one-minute takes (7200 frames at 120 Hz)
    python -m bench.batch --takes 8 --frames 3600

Takes are DESIGN's active human ROM (1 mm noise, 2 mm soft tissue, gaps), four
generated subjects in turn; they are written as C3D into a temporary folder and
fitted by :func:`mocapskel.batch.run_batch` without the artifact cache. The
wall time covers the whole batch (worker start-up included, not the
generation). Prints a markdown table; with ``--json`` a last line of JSON.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

from bench.common import machine, table

SUBJECTS = ((1, 1.0), (2, 1.05), (4, 0.95), (7, 1.0))


def make_takes(folder: Path, n: int, frames: int) -> list[int]:
    """Write ``n`` takes into ``folder``; return the true subject of each (index into SUBJECTS)."""
    from mocapskel.io.markers import write_markers
    from mocapskel.synth.presets import active_rom, make

    truth = []
    for i in range(n):
        k = i % len(SUBJECTS)
        subject_seed, scale = SUBJECTS[k]
        take = make(active_rom(seed=1000 + i, frames=frames, subject_seed=subject_seed, scale=scale))
        name = f"take{i:02d}.c3d"
        write_markers(folder / name, replace(take.markers, source=name))
        truth.append(k)
    return truth


def _load() -> str:
    try:
        return " / ".join(f"{x:.1f}" for x in os.getloadavg())
    except OSError:  # pragma: no cover - not on every system
        return "n/a"


def _cpu_seconds() -> float:
    """CPU time (user + system) of this process and of its finished children so far."""
    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def _agreement(found: list[str], truth: list[int]) -> bool:
    """True when the found subjects are the true ones up to naming."""
    pairs = set(zip(found, truth))
    return len(pairs) == len(set(found)) == len(set(truth))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--takes", type=int, default=20)
    ap.add_argument("--frames", type=int, default=7200)
    ap.add_argument("--jobs", default="1,2", help="worker counts to compare, the first is the reference")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)

    from mocapskel.batch import BatchOptions, run_batch, warm_up

    warm_up()  # the in-process run (1 worker) should not pay the imports either
    jobs_list = [int(j) for j in args.jobs.split(",")]
    results = []
    with tempfile.TemporaryDirectory(prefix="mocapskel-bench-batch-") as tmp:
        d = Path(tmp)
        takes = d / "takes"
        takes.mkdir()
        print(f"generating {args.takes} takes of {args.frames} frames …", file=sys.stderr)
        truth = make_takes(takes, args.takes, args.frames)
        for jobs in jobs_list:
            load_before = _load()
            print(f"fitting with {jobs} worker(s) …", file=sys.stderr)
            t, cpu = time.perf_counter(), _cpu_seconds()
            res = run_batch([takes], d / f"out{jobs}", BatchOptions(use_cache=False), jobs=jobs)
            wall, cpu = time.perf_counter() - t, _cpu_seconds() - cpu
            rows = res.rows
            fit_s = sum(float(r["seconds"]) for r in rows)
            results.append({
                "jobs": jobs, "takes": len(rows), "failed": res.failed, "wall_s": wall,
                "per_take_s": wall / len(rows), "sum_take_s": fit_s, "cpu_s": cpu, "load_before": load_before,
                "subjects_found": res.subjects.n_subjects if res.subjects else 0,
                "subjects_right": _agreement([r["subject"] for r in rows], truth),
                "subjects_true": len(set(truth)),
            })
            print(f"  {wall:.1f} s", file=sys.stderr)
    ref = results[0]["wall_s"]
    for r in results:
        r["speedup"] = ref / r["wall_s"]
    print(f"Machine: {machine()}.  ")
    print(f"{args.takes} takes of {args.frames} frames ({args.frames / 120:.0f} s at 120 Hz), active human ROM "
          f"(1 mm noise, 2 mm soft tissue, gaps), {len(set(range(min(args.takes, len(SUBJECTS)))))} subjects; no cache.\n")
    print(table(
        ["workers", "takes", "failed", "wall (s)", "s per take", "speedup", "takes in flight", "CPU (s)", "CPU / wall",
         "subjects found (true)", "load avg before"],
        [[r["jobs"], r["takes"], r["failed"], round(r["wall_s"], 1), round(r["per_take_s"], 2),
          f"{r['speedup']:.2f}×", round(r["sum_take_s"] / r["wall_s"], 2), round(r["cpu_s"], 1), round(r["cpu_s"] / r["wall_s"], 2), f"{r['subjects_found']} ({r['subjects_true']}){'' if r['subjects_right'] else ', mixed'}",
          r["load_before"]] for r in results],
    ))
    print("\nTakes in flight: the takes' own times added up, over the wall time (how many were being fitted at "
          "once). CPU: user + system time of the batch and its worker processes; CPU / wall near the worker count "
          "means the cores were the batch's alone. Load average: the machine's, before each run.")
    if args.json:
        print(json.dumps(results))


if __name__ == "__main__":
    main()
