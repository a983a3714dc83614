"""Every real take of ``../shared/realdata/`` through ``mocapskel fit``: what it makes of them.

    python -m bench.realdata                      # markdown to stdout (nothing when the folder is absent)
    python -m bench.realdata --joint-model map    # the same with that option of ``fit``

No take has a reference skeleton, so this reports what can be judged without
one: whether the fit succeeds (or the documented error), how many segments it
finds and how many clustered groups it had to split for rigidity, how well
the fitted skeleton explains the markers (IK marker rms), and the time. Each
take runs ``mocapskel fit`` in a fresh process.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench.common import REPO, table

REALDATA = REPO.parent / "shared" / "realdata"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--joint-model", default=None, help="passed to fit (its default when not given)")
    args = ap.parse_args()
    extra = [] if args.joint_model is None else ["--joint-model", args.joint_model]
    if not REALDATA.is_dir():
        print("(the real-take folder is absent: nothing measured)\n")
        return
    files = sorted(p for p in REALDATA.rglob("*") if p.is_file() and p.suffix.lower() in (".c3d", ".trc"))
    exe = str(Path(sys.executable).parent / "mocapskel")
    rows = []
    for p in files:
        rel = str(p.relative_to(REALDATA))
        with tempfile.TemporaryDirectory() as d:
            rep = Path(d) / "r.json"
            t = time.perf_counter()
            r = subprocess.run([exe, "fit", str(p), "-o", str(Path(d) / "o.bvh"), "--report", str(rep), "--no-cache", "-q", *extra],
                               capture_output=True, text=True)
            wall = time.perf_counter() - t
            if r.returncode == 0:
                d_ = json.loads(rep.read_text())
                ref = d_.get("refinement") or {}
                rows.append([rel, "ok", d_["input"]["frames"], d_["input"]["markers"], len(d_["segments"]),
                             len(d_.get("segments_moved", [])), len(d_.get("segments_split", [])),
                             round(d_["ik"]["marker_rms_mm"], 1),
                             round(ref["marker_rms_mm_after"], 1) if ref else "",
                             ", ".join(f"{v:g}" for v in (ref.get("mean_within_mm") or {}).values()),
                             len(d_.get("warnings", [])), round(wall, 1)])
            else:
                err = r.stderr.strip().splitlines()[-1] if r.stderr.strip() else ""
                rows.append([rel, f"exit {r.returncode}: {err.split(': ', 2)[-1][:90]}", "", "", "", "", "", "", "", "", "",
                             round(wall, 1)])
        print(f"  {rows[-1]}", file=sys.stderr)
    print("Every take of `../shared/realdata/` (see its README), `mocapskel fit TAKE -o out.bvh --no-cache` in a "
          "fresh process. IK rms: marker rms residual of the fitted skeleton over the take; refined: the same on the "
          "refinement's frames. Markers moved: markers the segment stage gave a place after the rigid grouping (a marker on a joint axis, or skin on its nearest group); groups split: groups that kept their distances but did not move as one body, split in two. Within the limb: joints whose prior's mean was brought back within their limb along their axis, by how much (mm, `refinement.mean_within_mm`). Warnings: the report's warnings, the output checks' findings among them (`python -m bench.checks` counts those by check).\n")
    print(table(["take", "result", "frames", "markers", "segments", "markers moved", "groups split", "IK rms (mm)",
                 "refined rms (mm)", "within the limb (mm)", "warnings",
                 "wall (s)"], rows))


if __name__ == "__main__":
    main()
