"""Real takes made messier: every take of ``../shared/realdata/`` cut short, thinned out, with markers
missing or a long gap, through ``mocapskel fit``.

    python -m bench.altered            # markdown to stdout (nothing when the folder is absent)

A real take that fits can still break when it is shorter, sparser or more broken than the ones at hand.
Each alteration is written as a C3D file and fitted by the command line in a fresh process; a result is
right when it is a BVH or one of the documented refusals (exit 4), never another exit code or a
traceback, and a BVH is judged by the output checks that say a skeleton is impossible (``bone_length``,
``joint_far``, ``residual``). The alterations are drawn with a fixed seed: the same files every run.
"""
from __future__ import annotations

import collections
import json
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np

from bench.common import REPO, table

REALDATA = REPO.parent / "shared" / "realdata"
#: The output checks that say no body has this skeleton.
IMPOSSIBLE = ("bone_length", "joint_far", "residual")
ALTERATIONS = {
    "first 40 frames": "the take's first 40 frames",
    "first 150 frames": "the take's first 150 frames",
    "every 5th frame": "one frame in five (the rate divided by five)",
    "40 % of markers gone": "a random 40 % of the markers left out",
    "a gap": "half of the markers unseen for the middle third of the take",
}


def altered(markers, rng: np.random.Generator) -> dict:
    """The alterations of one take (those that apply to it): {name: Markers}."""
    F, M, _ = markers.points.shape
    out = {}
    for n in (40, 150):
        if F > n:
            out[f"first {n} frames"] = replace(markers, points=markers.points[:n].copy())
    out["every 5th frame"] = replace(markers, points=markers.points[::5].copy(), rate=markers.rate / 5)
    keep = np.sort(rng.choice(M, max(2, int(M * 0.6)), replace=False))
    out["40 % of markers gone"] = replace(markers, points=markers.points[:, keep].copy(),
                                         labels=tuple(markers.labels[i] for i in keep))
    p = markers.points.copy()
    p[F // 3: F // 3 + F // 3, rng.choice(M, max(1, M // 2), replace=False)] = np.nan
    out["a gap"] = replace(markers, points=p)
    return out


def _fit(path: Path) -> tuple[int, str, dict | None]:
    exe = str(Path(sys.executable).parent / "mocapskel")
    rep = path.with_suffix(".json")
    r = subprocess.run([exe, "fit", str(path), "-o", str(path.with_suffix(".bvh")), "--report", str(rep), "--no-cache",
                        "-q"], capture_output=True, text=True)
    return r.returncode, r.stderr, (json.loads(rep.read_text()) if r.returncode == 0 and rep.is_file() else None)


def main() -> None:
    if not REALDATA.is_dir():
        print("(the real-take folder is absent: nothing measured)\n")
        return
    from mocapskel.io.markers import read_markers, write_markers

    files = sorted(p for p in REALDATA.rglob("*") if p.is_file() and p.suffix.lower() in (".c3d", ".trc"))
    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory() as d:
        jobs = []
        for p in files:
            for k, (name, m) in enumerate(altered(read_markers(p), rng).items()):
                out = Path(d) / f"{p.stem}.{k}.c3d"
                write_markers(out, replace(m, source=out.name))
                jobs.append((str(p.relative_to(REALDATA)), name, out))
        with ThreadPoolExecutor(2) as ex:
            results = list(ex.map(lambda j: _fit(j[2]), jobs))
    per = collections.defaultdict(lambda: collections.Counter())
    bad_rows, wrong_rows = [], []
    for (rel, name, _), (code, err, rep) in zip(jobs, results):
        c = per[name]
        c["takes"] += 1
        if code == 0 and "Traceback" not in err:
            c["fitted"] += 1
            found = collections.Counter(f["check"] for f in rep["checks"] if f["check"] in IMPOSSIBLE)
            if found:
                c["impossible"] += 1
                bad_rows.append([rel, name, len(rep["segments"]), round(rep["ik"]["marker_rms_mm"], 1),
                                 ", ".join(f"{k} {v}" for k, v in sorted(found.items()))])
        elif code == 4 and "Traceback" not in err:
            c["refused"] += 1
            c["why: " + _reason(err)] += 1
        else:
            c["wrong"] += 1
            wrong_rows.append([rel, name, code, (err.strip().splitlines() or [""])[-1][:120]])
        print(f"  {rel} / {name}: exit {code}", file=sys.stderr)
    print(f"Every take of `../shared/realdata/` altered five ways ({'; '.join(f'{k}: {v}' for k, v in ALTERATIONS.items())}; "
          "random choices from one seed), written as C3D and fitted with `mocapskel fit ALTERED.c3d -o out.bvh --no-cache` "
          "in a fresh process. Right: a BVH or a documented refusal (exit 4); wrong: any other exit code or a traceback. "
          f"Impossible: a BVH whose output checks say no body has it ({', '.join(IMPOSSIBLE)}).\n")
    rows = []
    for name in ALTERATIONS:
        c = per[name]
        why = "; ".join(f"{k[5:]} {v}" for k, v in sorted(c.items()) if k.startswith("why: "))
        rows.append([name, c["takes"], c["fitted"], c["refused"], why, c["wrong"], c["impossible"]])
    print(table(["alteration", "takes", "fitted", "refused (exit 4)", "refused because", "wrong", "fitted but impossible"],
                rows))
    if wrong_rows:
        print("\nWrong results:\n")
        print(table(["take", "alteration", "exit code", "last line"], wrong_rows))
    if bad_rows:
        print("\nFitted but impossible:\n")
        print(table(["take", "alteration", "segments", "IK rms (mm)", "checks"], bad_rows))


def _reason(err: str) -> str:
    """The kind of a refusal, from its message."""
    msg = err.strip().splitlines()[-1] if err.strip() else ""
    for key, what in (("visible run", "too short"), ("one rigid body", "one rigid body"), ("nothing moves", "nothing moves"),
                      ("single marker", "one marker a segment"), ("too few", "too few markers or frames"),
                      ("never seen well enough", "a segment never seen well enough to fit"),
                      ("seen often enough", "too few markers seen often enough")):
        if key in msg:
            return what
    return msg.split(": ", 3)[-1][:60]


if __name__ == "__main__":
    main()
