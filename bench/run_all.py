"""Run every benchmark and rewrite BENCHMARKS.md (`make bench`).

The sections of the benchmarks run here are written anew; every other section of BENCHMARKS.md (those of benchmarks
too slow for `make bench`, run by hand with the command they name: the joint models, the joints' uncertainty) is kept
as it is, after them."""
from __future__ import annotations

import datetime
import subprocess
import sys

from bench.common import REPO, machine

BENCHES = [
    ("Accuracy and time of `fit` on generated takes", "bench.accuracy"),
    ("Speed and memory", "bench.speed"),
    ("Joint-centre estimators against the papers", "bench.joints"),
    ("Passive data: merge-ids", "bench.passive"),
    ("Batches: local workers", "bench.batch"),
    ("Real takes", "bench.realdata"),
    ("Real takes made messier", "bench.altered"),
    ("Euler spikes in the written BVH", "bench.euler_spikes"),
    ("Output checks: real and generated takes", "bench.checks"),
    ("Humanoid names", "bench.names"),
    ("Generated takes that look like real captures", "bench.realistic"),
    ("Real takes with a reference skeleton", "bench.realref"),
    ("Real takes scored by their anatomical landmarks", "bench.realanat"),
]


def kept_sections(text: str, titles: set[str]) -> list[str]:
    """The ``## `` sections of ``text`` whose titles are not in ``titles``, each whole, in order."""
    out: list[str] = []
    for block in ("\n" + text).split("\n## ")[1:]:
        title = block.split("\n", 1)[0].strip()
        if title not in titles:
            out.append("## " + block.rstrip("\n") + "\n")
    return out


def main() -> None:
    path = REPO / "BENCHMARKS.md"
    kept = kept_sections(path.read_text(), {t for t, _ in BENCHES}) if path.exists() else []
    parts = [
        "# Benchmarks\n",
        f"Machine: {machine()}.  ",
        f"Date: {datetime.date.today().isoformat()}.  ",
        "Command: `make bench` (each section below is `python -m <module>`; every fit runs in a fresh process).\n",
    ]
    for title, module in BENCHES:
        print(f"running {module} …", file=sys.stderr)
        out = subprocess.run([sys.executable, "-m", module], cwd=REPO, capture_output=True, text=True)
        parts.append(f"## {title}\n\n`python -m {module}`\n")
        parts.append(out.stdout if out.returncode == 0 else f"FAILED:\n```\n{out.stderr[-3000:]}\n```\n")
    parts.extend(kept)
    path.write_text("\n".join(parts) + "\n")
    print("wrote BENCHMARKS.md", file=sys.stderr)


if __name__ == "__main__":
    main()
