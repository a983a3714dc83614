"""How much of a fit's marker residual follows the joint angles: skin that slides with the joints, or a
skeleton the take does not have, against noise the model describes.

    python -m bench.skin_share                 # markdown to stdout: generated takes, then real ones
    python -m bench.skin_share --only real     # one half

Each take is fitted up to the rigid stage with the model's MAP (``rigid.Params(joint_model="map")``;
generated takes with their true grouping and tree handed in). On the refinement's frames, every marker's
residual (observed minus the fitted skeleton's, in its segment's axes) is regressed on its segment's joint
angles (the rotation vectors to its parent and children, centred) and their products (a quadratic in the
angles). The share is the variance that regression explains beyond what as many random regressors would
(the adjusted R^2, pooled over markers). Noise that does not depend on the pose gives about 0; skin moved by
the joint angles gives the part of it that a shifted joint centre cannot absorb (a joint centre moved by c
moves a marker by (I - R(theta)) c, linear in theta for small turns: that part of the skin's motion is taken
into the joint's place and never seen in the residual).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from bench.common import REPO, run_isolated, table

SEEDS = (1, 2, 3, 4, 5, 6)
MOTIONS = ("rom", "walk", "run", "kick", "reach")
REALREF = REPO.parent / "shared" / "realref"
REALDATA = REPO.parent / "shared" / "realdata"
REAL = ("realref/opensim_test_walking.c3d", "realref/cmu_16_07.c3d", "realref/kinova_dynamique_pierre.c3d",
        "realdata/hdm05/HDM_bd_05-01_01_120.c3d", "realdata/joint-localization/fullbody_44Markers_clean_120fps.c3d",
        "realdata/joint-localization/arm-4-4-4_clean_30fps.c3d")


def angle_share(skel) -> dict:
    """{"share": pooled adjusted R^2, "residual_mm": rms residual length, "frames": n} of a refined skeleton."""
    from mocapskel.solvers.model.calibrate import _Problem
    from mocapskel.solvers.rotations import matrix_to_rotvec

    use, R, p = skel.pose_frames, skel.pose_rot, skel.pose_root
    obs = skel.joints.topology.segments.markers.points[use]
    S = len(skel.parent)
    pr = _Problem(skel.parent, skel.marker_segment, obs)
    d = np.zeros((S, 3))
    for c in pr.kids:
        d[c] = skel.origin[c] - skel.origin[skel.parent[c]]
    _, _, x = pr.fk(p, R, d, skel.marker_local)
    res = obs[:, pr.used] - x
    total = explained = 0.0
    for i, m in enumerate(pr.used):
        s = int(skel.marker_segment[m])
        r = np.einsum("fji,fj->fi", R[:, s], res[:, i])  # in the segment's axes
        nbs = ([int(skel.parent[s])] if skel.parent[s] >= 0 else []) + [int(c) for c in np.flatnonzero(skel.parent == s)]
        if not nbs:
            continue
        th = np.concatenate([matrix_to_rotvec(np.einsum("fji,fjk->fik", R[:, s], R[:, nb])) for nb in nbs], 1)
        ok = np.isfinite(r).all(1) & np.isfinite(th).all(1)
        th = th[ok] - th[ok].mean(0)
        k = th.shape[1]
        iu = np.triu_indices(k)
        X = np.concatenate([np.ones((len(th), 1)), th, (th[:, :, None] * th[:, None, :])[:, iu[0], iu[1]]], 1)
        y = r[ok]
        n, q = X.shape
        if n < 3 * q:
            continue
        beta, *_ = np.linalg.lstsq(X, y, rcond=None)
        ss = float(((y - y.mean(0)) ** 2).sum())
        se = float(((X @ beta - y.mean(0)) ** 2).sum())
        total += ss
        explained += se - ss * (q - 1) / (n - 1)  # less what q - 1 random regressors explain on average
    return {"share": explained / total if total > 0 else float("nan"),
            "residual_mm": float(np.sqrt(3 * np.nanmean(res**2))), "frames": int(use.size)}


def generated_case(motion: str, seed: int) -> dict:
    from mocapskel import evaluate, pipeline
    from mocapskel.stages import rigid
    from mocapskel.synth.presets import active_rom, make, realistic

    if motion == "rom48":
        take = make(active_rom(seed, frames=3600))
    else:
        take = make(realistic(seed=seed, frames=600, motion=motion, markerset="cmu41"))
    clean = pipeline.run_until(take.markers, "clean").artifact
    joints = pipeline.run_until(evaluate.true_topology(take.truth, clean), "joints").artifact
    skel = pipeline.run_until(joints, "rigid", {"rigid": rigid.Params(joint_model="map")}).artifact
    return angle_share(skel)


def real_case(rel: str) -> dict:
    from mocapskel import pipeline
    from mocapskel.stages import rigid

    path = REPO.parent / "shared" / rel
    if not path.exists():
        return {"error": "absent"}
    params = pipeline.make_params(up="z", units="mm")
    params["rigid"] = rigid.Params(joint_model="map")
    return angle_share(pipeline.run_until(path, "rigid", params).artifact)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--only", choices=["gen", "real"])
    ap.add_argument("--json", action="store_true", help=argparse.SUPPRESS)  # set by run_isolated
    ap.add_argument("--case", nargs="+", help=argparse.SUPPRESS)  # internal: one case, JSON out
    a = ap.parse_args()
    if a.case:
        out = real_case(a.case[1]) if a.case[0] == "real" else generated_case(a.case[0], int(a.case[1]))
        print(json.dumps(out))
        return
    if a.only != "real":
        rows = []
        for motion in ("rom48", *MOTIONS):
            got = [run_isolated("skin_share", "--case", motion, str(s)) for s in SEEDS]
            print(f"  {motion}: {[round(g['share'], 3) for g in got]}", file=sys.stderr)
            rows.append(["48-marker ROM (soft tissue independent of the pose)" if motion == "rom48"
                         else f"realistic cmu41 {motion} (skin driven by the joint angles)",
                         " ".join(f"{g['share']:.2f}" for g in got),
                         f"{np.median([g['residual_mm'] for g in got]):.2f}"])
        print("### Generated takes (the true grouping and tree; seeds 1-6)\n")
        print(table(["take", "share per seed", "median rms residual (mm)"], rows))
    if a.only != "gen":
        rows = []
        for rel in REAL:
            g = run_isolated("skin_share", "--case", "real", rel)
            if "error" in g:
                print(f"  {rel}: ABSENT (../shared/ not here)", file=sys.stderr)
                continue
            rows.append([Path(rel).name, f"{g['share']:.2f}", f"{g['residual_mm']:.2f}", g["frames"]])
        print("\n### Real takes (grouping and tree found)\n")
        print(table(["take", "share", "rms residual (mm)", "frames"], rows))


if __name__ == "__main__":
    main()
