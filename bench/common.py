"""Helpers shared by the benchmarks: machine facts, timing, peak memory, markdown."""
from __future__ import annotations

import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def compile_package(root: Path = REPO) -> None:
    """Write the bytecode of the package in the checkout ``root``, as installing it does: the fits in
    fresh processes then time what a user's installed command does, not compiling the package (a
    third of a second, again in every process where ``PYTHONDONTWRITEBYTECODE`` is set, which keeps
    Python from writing it on import)."""
    import compileall

    compileall.compile_dir(str(root / "mocapskel"), quiet=1)


compile_package()


def machine() -> str:
    mem = ""
    try:
        with open("/proc/meminfo") as f:
            kb = int(f.readline().split()[1])
            mem = f"{kb / 2**20:.0f} GiB"
    except OSError:
        pass
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    import numpy

    return f"{os.cpu_count()} cores ({cpu}), {mem} memory, Python {platform.python_version()}, numpy {numpy.__version__}"


def median_time(fn: Callable[[], object], repeats: int = 3) -> tuple[float, object]:
    """Median wall time of ``repeats`` calls, and the last result."""
    times, out = [], None
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times), out


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far (MB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def run_isolated(module: str, *args: str) -> dict:
    """Run ``python -m bench.<module> --json ARGS`` in a fresh process; its last stdout line is JSON."""
    cmd = [sys.executable, "-m", f"bench.{module}", "--json", *args]
    out = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def table(header: list[str], rows: list[list]) -> str:
    def fmt(v):
        if isinstance(v, float):
            return f"{v:.3g}" if abs(v) < 1e4 else f"{v:.0f}"
        return str(v)

    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(fmt(v) for v in r) + " |" for r in rows]
    return "\n".join(lines)
