"""``fit`` on generated takes that look like real captures (real marker sets, skin motion driven by the
joint angles, everyday motions, 1 mm noise), scored against their ground truth.

    python -m bench.realistic            # markdown to stdout
    python -m bench.realistic --json --case cmu41 walk 1 1200   # one case (internal)

Every case is generated in one fresh process and fitted from a C3D file in another (as ``mocapskel
fit`` runs). The second table compares the generated skin with real CMU takes (when the folder of real
takes is present): the standard deviation over frames of distances between markers that real marker
sets put on one segment, or across one joint.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from bench.common import REPO, run_isolated, table

CASES = [("cmu41", m, s) for m in ("walk", "run", "kick", "reach", "rom") for s in (1, 2, 3)] + \
        [("gait", "walk", s) for s in (1, 2)] + [("cluster", "walk", 1), ("cluster", "reach", 1)]
FRAMES = 600
REAL_CMU = REPO.parent / "shared" / "realdata" / "cmu"
REAL_REF = REPO.parent / "shared" / "realref"
PAIRS = [("LTHI", "LKNE"), ("LKNE", "LSHN"), ("LSHN", "LANK"), ("LKNE", "LANK"), ("LFWT", "LTHI"), ("LUPA", "LELB"),
         ("LELB", "LFRM"), ("LFRM", "LWRA"), ("LWRA", "LWRB"), ("LWRB", "LFIN"), ("LANK", "LHEE"), ("LHEE", "LTOE"),
         ("LFHD", "LBHD"), ("C7", "CLAV"), ("C7", "T10"), ("CLAV", "STRN"), ("LFWT", "RFWT"), ("LFWT", "LBWT"),
         ("LSHO", "C7"), ("LSHO", "LUPA"), ("LUPA", "LWRA"), ("RUPA", "RWRA")]  # fmt: skip


def _segments_either(marker_segment: np.ndarray, labels: tuple[str, ...], truth) -> tuple[bool, int]:
    """Marker groups right when a marker on a joint may go with either of the joint's segments.

    Returns (right, number of groups)."""
    names = list(truth.segment_names)
    phys = truth.info["physical_labels"]
    allowed = {lab: {names.index(n) for n in ok if n in names} for lab, ok in zip(phys, truth.info["marker_segments_ok"])}
    groups = sorted(set(int(g) for g in marker_segment if g >= 0))
    used: set[int] = set()
    for g in groups:
        labs = [labels[i] for i in np.flatnonzero(marker_segment == g)]
        common = set.intersection(*(allowed[l] for l in labs if l in allowed)) if labs else set()
        hosts = [int(truth.marker_segment[phys.index(l)]) for l in labs if l in phys]
        pick = [s for s in common if s not in used]
        if not pick:
            return False, len(groups)
        major = max(set(hosts), key=hosts.count) if hosts else pick[0]
        used.add(major if major in pick else pick[0])
    return len(used) == len(names) and all(int(g) >= 0 for g in marker_segment), len(groups)


def case(markerset: str, motion: str, seed: int, frames: int, write: str | None) -> dict | None:
    from mocapskel.io.markers import write_markers
    from mocapskel.synth.presets import make, realistic

    if write:
        take = make(realistic(seed=seed, frames=frames, motion=motion, markerset=markerset))
        path = Path(write) / "take.c3d"
        write_markers(path, replace(take.markers, source=path.name))
        take.truth.save(Path(write) / "truth.npz")
        return None
    from mocapskel import evaluate, pipeline
    from mocapskel.errors import MocapskelError
    from mocapskel.synth.truth import Truth

    with tempfile.TemporaryDirectory() as d:
        subprocess.run([sys.executable, "-m", "bench.realistic", "--case", markerset, motion, str(seed), str(frames),
                        "--write", d], check=True, cwd=REPO)
        truth = Truth.load(Path(d) / "truth.npz")
        t = time.perf_counter()
        try:
            res = pipeline.fit(Path(d) / "take.c3d", pipeline.make_params(up="z", units="mm"))
        except MocapskelError as e:
            return {"error": str(e).splitlines()[0][:80], "total_s": time.perf_counter() - t,
                    "true_segments": len(truth.segment_names)}
        total = time.perf_counter() - t
    skel = res.motion.skeleton
    sc = evaluate.score_motion(res.motion, truth)
    sj = evaluate.score_joints(skel.joints, truth)
    either, n_groups = _segments_either(np.asarray(skel.marker_segment), tuple(skel.labels), truth)
    bones = [abs(v) for v in sc.bone_err.values() if np.isfinite(v)]
    return {
        "segments_found": n_groups, "true_segments": len(truth.segment_names),
        "segments_strict": bool(sc.segments_ok), "segments_either": bool(either), "topology_ok": bool(sc.topology_ok),
        "joints_matched": len(sc.joint_rms_each), "true_joints": int(truth.joint_child.size),
        "joint_rms_mm": sc.joint_rms_mm, "joint_rms_joints_stage_mm": sj.joint_rms_mm,
        "bone_err_mean": float(np.mean(bones)) if bones else float("nan"),
        "bone_err_max": float(np.max(bones)) if bones else float("nan"), "n_bones": len(bones),
        "ik_rms_mm": res.report["ik"]["marker_rms_mm"], "total_s": total,
    }


# a limb out of view, as when the subject walks into or out of the capture volume, or turns an arm behind
# the body: every marker of the left forearm and hand over the take's first fifth, of the right foot over its
# last fifth
HIDDEN = (("LELB", "LFRM", "LWRA", "LWRB", "LFIN"), ("RHEE", "RTOE", "RMT5"))
HIDDEN_CASES = [("cmu41", m, s) for m in ("walk", "run", "kick") for s in (1, 2, 3)]


def hidden_case(markerset: str, motion: str, seed: int, frames: int) -> dict:
    """Fit a realistic take with :data:`HIDDEN` limbs out of view; where the skeleton puts their markers."""
    from mocapskel import evaluate, pipeline
    from mocapskel.synth.presets import make, realistic

    take = make(realistic(seed=seed, frames=frames, motion=motion, markerset=markerset))
    labels = list(take.markers.labels)
    pts = take.markers.points.copy()
    hidden = np.zeros(pts.shape[:2], dtype=bool)
    k = frames // 5
    hidden[:k, [labels.index(m) for m in HIDDEN[0]]] = True
    hidden[frames - k:, [labels.index(m) for m in HIDDEN[1]]] = True
    pts[hidden] = np.nan
    res = pipeline.fit(replace(take.markers, points=pts), pipeline.make_params(up="z", units="mm"))
    mot = res.motion
    skel = mot.skeleton
    J = evaluate.joint_positions(mot)
    err = []
    for m, lab in enumerate(skel.labels):
        s = int(skel.marker_segment[m])
        i = labels.index(lab)
        if s < 0 or not hidden[:, i].any():
            continue
        x = J[hidden[:, i], s] + np.einsum("fij,j->fi", mot.rot[hidden[:, i], s], skel.marker_local[m])
        err.append(np.linalg.norm(x - take.markers.points[hidden[:, i], i], axis=1))
    e = np.concatenate(err) if err else np.full(1, np.nan)
    sc = evaluate.score_motion(mot, take.truth)
    steps = [w for w in res.report["warnings"] if w.startswith("check joint_step") or w.startswith("check rotation_flip")]
    return {"hidden_rms_mm": float(np.sqrt(np.mean(e**2))), "hidden_p95_mm": float(np.percentile(e, 95)),
            "hidden_markers": len(err), "joint_rms_mm": sc.joint_rms_mm, "step_warnings": len(steps)}


def hidden() -> str:
    rows = []
    for markerset, motion, seed in HIDDEN_CASES:
        r = run_isolated("realistic", "--hidden-case", markerset, motion, str(seed), str(FRAMES))
        rows.append([markerset, motion, seed, f"{r['hidden_markers']} / {sum(map(len, HIDDEN))}",
                     round(r["hidden_rms_mm"], 1), round(r["hidden_p95_mm"], 1), round(r["joint_rms_mm"], 1),
                     r["step_warnings"]])
        print(f"  {rows[-1]}", file=sys.stderr)
    return table(["marker set", "motion", "seed", "hidden markers on the skeleton", "their rms error (mm)",
                  "95th percentile (mm)", "joint rms after IK (mm)", "jump and flip warnings"], rows)


def fits() -> str:
    rows = []
    for markerset, motion, seed in CASES:
        r = run_isolated("realistic", "--case", markerset, motion, str(seed), str(FRAMES))
        if "error" in r:
            rows.append([markerset, motion, seed, f"error: {r['error']}", "", "", "", "", "", "", "", round(r["total_s"], 1)])
        else:
            rows.append([markerset, motion, seed, f"{r['segments_found']} / {r['true_segments']}",
                         "yes" if r["segments_either"] else "NO", "yes" if r["topology_ok"] else "NO",
                         f"{r['joints_matched']} / {r['true_joints']}", round(r["joint_rms_joints_stage_mm"], 1),
                         round(r["joint_rms_mm"], 1), round(100 * r["bone_err_mean"], 1), round(100 * r["bone_err_max"], 1),
                         round(r["total_s"], 1)])
        print(f"  {rows[-1]}", file=sys.stderr)
    return table(["marker set", "motion", "seed", "segments found / true", "grouping right", "tree right",
                  "joints matched", "joint rms, joints stage (mm)", "joint rms after IK (mm)", "mean bone error (%)",
                  "worst bone error (%)", "fit time (s)"], rows)


def _pair_std(points: np.ndarray, labels) -> list[float]:
    labs = [str(l).split(":")[-1] for l in labels]
    out = []
    for a, b in PAIRS:
        if a in labs and b in labs:
            out.append(float(np.nanstd(np.linalg.norm(points[:, labs.index(a)] - points[:, labs.index(b)], axis=1))))
        else:
            out.append(float("nan"))
    return out


def skin_vs_real() -> str:
    from mocapskel.io.markers import read_markers
    from mocapskel.synth.presets import make, realistic

    cols, data = [], []
    real = sorted(REAL_CMU.glob("*.c3d")) + ([REAL_REF / "cmu_16_07.c3d"] if (REAL_REF / "cmu_16_07.c3d").is_file() else [])
    if not real:
        return "(the real CMU takes are absent: no comparison)\n"
    for p in real:
        m = read_markers(p)
        cols.append(f"real {p.stem}")
        data.append(_pair_std(m.points, m.labels))
    for motion in ("walk", "run", "kick", "reach"):
        s = [_pair_std(t.markers.points, t.markers.labels) for t in
             (make(realistic(seed=seed, frames=FRAMES, motion=motion)) for seed in (1, 2, 3))]
        cols.append(f"generated {motion}")
        data.append(list(np.mean(s, axis=0)))
    rows = [[f"{a}-{b}"] + [round(d[i], 1) for d in data] for i, (a, b) in enumerate(PAIRS)]
    return table(["marker pair: std over frames of the distance (mm)"] + cols, rows)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--case", nargs=4, metavar=("MARKERSET", "MOTION", "SEED", "FRAMES"))
    ap.add_argument("--write", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--hidden-case", nargs=4, metavar=("MARKERSET", "MOTION", "SEED", "FRAMES"))
    ap.add_argument("--only-hidden", action="store_true", help="only the table of limbs out of view")
    a = ap.parse_args()
    if a.hidden_case:
        print(json.dumps(hidden_case(a.hidden_case[0], a.hidden_case[1], int(a.hidden_case[2]), int(a.hidden_case[3]))))
        return
    if a.only_hidden:
        print(hidden())
        return
    if a.case:
        out = case(a.case[0], a.case[1], int(a.case[2]), int(a.case[3]), a.write)
        if out is not None:
            print(json.dumps(out))
        return
    print(f"Realistic generated takes ({FRAMES} frames at 120 Hz, 1 mm noise, skin motion driven by the joint angles; "
          "`mocapskel synth human --markerset M --motion X --skin realistic --noise 1`), fitted from C3D with "
          "`--up z --units mm`. Grouping right: the true segments, a marker on a joint counted right with either of "
          "its joint's segments. Joints matched: true joints whose two segments the fitted tree joins.\n")
    print(fits())
    print("\nSkin motion, generated against real CMU takes (same labels; generated: mean of seeds 1-3; "
          "1 mm generated noise adds ~1.4 mm to every entry):\n")
    print(skin_vs_real())
    print("\nA limb out of view (the cmu41 walks, runs and kicks above; every marker of the left forearm and hand removed over the first "
          "fifth of the take, of the right foot over its last fifth, as when the subject walks into or out of the "
          "volume): how far from where they truly were the fitted skeleton puts the removed markers, over the "
          "frames they are missing. Joint rms over the whole take.\n")
    print(hidden())


if __name__ == "__main__":
    main()
