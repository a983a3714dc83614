"""The real takes with another party's skeleton (``../shared/realref/``), scored.

    python -m bench.realref            # markdown to stdout (a note when the folder is absent)

Each take is fitted by ``python -m mocapskel fit TAKE -o NAME.bvh --up z --units mm`` (this checkout) in a
fresh process and the BVH scored with that folder's ``score.py`` (see its
README for what each reference is worth). The two unlabelled arm takes of
``../shared/realdata/joint-localization/`` whose grouping their author gives
are checked for exactly that grouping.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench.common import REPO, table

REALREF = REPO.parent / "shared" / "realref"
REALDATA = REPO.parent / "shared" / "realdata"

#: The groupings the arm takes' author gives (marker indices in file order; ../shared/realref/README.md).
ARM_GROUPS = {
    "joint-localization/arm-4-4-4_clean_30fps.c3d": [[0, 1, 2, 3], [4, 5, 6, 7], [8, 9, 10, 11]],
    "joint-localization/arm-4-2-3_clean_120fps.c3d": [[0, 1, 2, 3], [4, 5], [6, 7, 8]],
}


def fit_and_score(name: str, folder: Path) -> tuple[dict, dict, float]:
    """(score, report, wall seconds) of one reference take."""
    # this checkout's package, first on the path (the installed ``mocapskel`` script imports whatever checkout
    # was installed, which need not be the one measured)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH", "")])))
    with tempfile.TemporaryDirectory() as d:
        bvh, rep = Path(d) / f"{name}.bvh", Path(d) / f"{name}.json"
        t = time.perf_counter()
        r = subprocess.run([sys.executable, "-m", "mocapskel", "fit", str(folder / f"{name}.c3d"), "-o", str(bvh),
                            "--up", "z", "--units", "mm", "--report", str(rep), "--no-cache", "-q"],
                           capture_output=True, text=True, env=env)
        wall = time.perf_counter() - t
        if r.returncode != 0:
            return {"error": r.stderr.strip().splitlines()[-1] if r.stderr.strip() else f"exit {r.returncode}"}, {}, wall
        s = subprocess.run([sys.executable, str(folder / "score.py"), name, str(bvh)], capture_output=True, text=True)
        return json.loads(s.stdout.strip().splitlines()[-1]), json.loads(rep.read_text()), wall


def groups_of(path: Path) -> list[list[int]]:
    """The segments ``fit`` finds for a take, as sorted lists of marker indices (file order)."""
    from mocapskel import pipeline

    seg = pipeline.run_until(path, "segment").artifact
    return sorted(sorted(int(i) for i in seg.members(s)) for s in range(seg.n_segments))


def main() -> None:
    if not (REALREF / "score.py").is_file():
        print("(the reference folder `../shared/realref/` is absent: nothing measured)\n")
        return
    names = sorted(p.name[: -len(".ref.npz")] for p in REALREF.glob("*.ref.npz"))
    rows = []
    for name in names:
        sc, rep, wall = fit_and_score(name, REALREF)
        print(f"  {name}: {sc.get('error') or 'scored'} ({wall:.1f} s)", file=sys.stderr)
        if "error" in sc:
            rows.append([name, sc["error"][:80], "", "", "", "", round(wall, 1)])
            continue
        segs = len(rep.get("segments", []))
        if sc["kind"] == "joints":
            found = f"{sc['joints_matched']} of {sc['joints_ref']} joints"
            rms, bone = sc["joint_rms_mean_mm"], sc["bone_err_mm_mean"]
            missing = ", ".join(sc["unmatched_ref"]) or "—"
        else:
            within = [lk for lk in sc.get("links", []) if lk.get("err_pct", 1e9) <= 5.0]
            found = f"{sc['links_matched']} of {sc['links_ref']} links ({len(within)} within 5 %)"
            rms, bone = "", sc.get("bone_err_pct_mean")
            missing = ", ".join(f"{lk['link']} {lk['err_pct']:.1f} %" for lk in sc.get("links", [])) or "—"
        rows.append([name, found, rms, bone, segs, missing, round(wall, 1)])
    print("Each take: `mocapskel fit TAKE -o NAME.bvh --up z --units mm` in a fresh process, scored by "
          "`../shared/realref/score.py` (a reference joint matches a BVH joint within 100 mm mean distance; "
          "joint rms and bone error in mm over the matched joints; for the robot arm, link lengths in %).\n")
    print(table(["take", "found", "joint rms (mm)", "bone error (mm or %)", "segments", "unmatched / links", "wall (s)"],
                rows))
    arm = []
    for rel, want in ARM_GROUPS.items():
        p = REALDATA / rel
        if not p.is_file():
            continue
        got = groups_of(p)
        arm.append([rel, len(got), "yes" if got == sorted(want) else f"no: {got}"])
    if arm:
        print("\nUnlabelled arm takes whose grouping their author gives (`../shared/realref/README.md`):\n")
        print(table(["take", "segments", "the author's grouping"], arm))


if __name__ == "__main__":
    main()
