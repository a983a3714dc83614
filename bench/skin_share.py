"""How much of a fit's marker residual follows the joint angles: skin that slides with the joints, or a
skeleton the take does not have, against noise the model describes.

    python -m bench.skin_share                 # markdown to stdout: generated takes, then real ones
    python -m bench.skin_share --only real     # one half

Each take is fitted up to the rigid stage with the model's MAP, its joints rigid (``rigid.Params(joint_model="map",
soft_sigma=0.0)``: the residual of the model whose joints are fixed points;
generated takes with their true grouping and tree handed in), and its refinement's residual measured by
:func:`mocapskel.solvers.model.skin.skin_motion` (the report's ``uncertainty.skin_share`` measures the fit's
final skeleton the same way): noise that does not depend on the pose gives about 0; skin moved by the joint
angles gives the part of it that a shifted joint centre cannot absorb.
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
REAL = ("realref/opensim_test_walking.c3d", "realref/cmu_16_07.c3d", "realref/kinova_dynamique_pierre.c3d",
        "realdata/hdm05/HDM_bd_05-01_01_120.c3d", "realdata/joint-localization/fullbody_44Markers_clean_120fps.c3d",
        "realdata/joint-localization/arm-4-4-4_clean_30fps.c3d")


def angle_share(skel) -> dict:
    """{"share": :func:`~mocapskel.solvers.model.skin.skin_motion`'s, "residual_mm": the refinement's rms marker
    residual, "frames": n} of a refined skeleton, on its refinement's frames."""
    from mocapskel.solvers.model.skin import skin_motion

    use = skel.pose_frames
    obs = skel.joints.topology.segments.markers.points[use]
    share = skin_motion(skel.parent, skel.marker_segment, skel.origin, skel.marker_local, obs, skel.pose_rot,
                        skel.pose_root).share
    return {"share": share, "residual_mm": skel.info["refined"]["marker_rms_mm_after"], "frames": int(use.size)}


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
    skel = pipeline.run_until(joints, "rigid", {"rigid": rigid.Params(joint_model="map", soft_sigma=0.0)}).artifact
    return angle_share(skel)


def real_case(rel: str) -> dict:
    from mocapskel import pipeline
    from mocapskel.stages import rigid

    path = REPO.parent / "shared" / rel
    if not path.exists():
        return {"error": "absent"}
    params = pipeline.make_params(up="z", units="mm")
    params["rigid"] = rigid.Params(joint_model="map", soft_sigma=0.0)
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
