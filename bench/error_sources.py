"""Where a realistic take's joint error comes from: the prior's mean, or the likelihood itself.

    python -m bench.error_sources                      # markdown to stdout: seeds 1-3 / 4-6, every motion
    python -m bench.error_sources --seeds 1 2 --motions run walk --procs 2

Generated takes with the true grouping and tree handed in (cmu41, 600 frames, 1 mm noise, skin driven by the joint
angles). The fitted skeleton is compared with three refits of the same model on the same frames, each started at
the true joints (the fitted markers' offsets moved with them: each segment keeps its markers where they were) and
each posed by the IK stage as the fit is:

- **joints held at the truth**, the markers' offsets refitted: what IK leaves when every joint is right (the floor);
- **the prior's mean at the truth**: the model's own prior sigmas and soft joints as the fit measured them, the
  prior centred on the true joints instead of the joints stage's places (its other factors, like bones, limbs'
  lines, hinges along the axis and the plane of symmetry, left out): what the model reaches with a perfect mean;
- **no prior**: the likelihood alone (rigid segments, noise at one level), from the true joints: where the markers
  place the joints that they place at all.

The fit's error less the second column is what the prior's mean costs; the second less the first, what the
likelihood pulls the joints away from the truth where the prior is right.
"""
from __future__ import annotations

import argparse
from dataclasses import replace
from multiprocessing import get_context

import numpy as np

from bench.common import table

MOTIONS = ("walk", "run", "kick", "rom", "reach")
COLUMNS = ("fit", "held", "prior_at_truth", "no_prior")


def at_true_joints(skel, motion, truth):
    """``skel``'s origins moved to the true joints, each in its parent's frame (through the fit's IK poses, averaged
    over the frames), each segment's markers kept where they are."""
    from mocapskel import evaluate
    from mocapskel.solvers.joint_moves import _move_joint

    smap = evaluate.segment_map(skel.marker_segment, truth)
    pos = evaluate.joint_positions(motion)
    origin, local = skel.origin.copy(), skel.marker_local.copy()
    for s in map(int, np.flatnonzero(skel.parent >= 0)):  # origins are absolute: any order
        p = int(skel.parent[s])
        pair = {smap[s], smap[p]}
        e = next(e for e, c in enumerate(truth.joint_child) if {int(c), int(truth.parent[c])} == pair)
        target = skel.origin[p] + np.nanmean(np.einsum("fji,fj->fi", motion.rot[:, p], truth.joints[:, e] - pos[:, p]), 0)
        origin, local = _move_joint(origin, local, skel.marker_segment, s, target - origin[s])
    return origin, local


def refits(skel, fit, truth, points: np.ndarray) -> dict:
    """{column: the refit (:func:`~mocapskel.solvers.model.calibrate.refine_skeleton`'s result)} of ``skel`` (the rigid
    stage's) from the true joints on its refinement's frames of ``points``, ``fit`` its IK (see the module)."""
    from mocapskel.solvers.model.calibrate import refine_skeleton

    origin, local = at_true_joints(skel, fit, truth)
    S = len(skel.names)
    use = skel.pose_frames
    ref = skel.info["refined"]
    kw = dict(iterations=60, ref_frame=int(np.searchsorted(use, skel.rest_frame)), anchor=(origin, local))
    args = (skel.parent, origin, skel.marker_segment, local, points[use], skel.pose_rot, skel.pose_root)
    held = np.zeros((S, 2))
    held[skel.parent >= 0] = 1e6  # every joint held where it starts, in both of its segments' frames
    noise2 = ref["soft_noise_mm"] ** 2  # the noise variance the data term sees (the data's weight in it)
    prior = np.zeros((S, 2))
    for k, sig in ref["prior_sigma_mm"].items():
        prior[skel.names.index(k)] = [noise2 / x**2 if x else 0.0 for x in sig]
    soft = {skel.names.index(n): noise2 / s**2 for n, s in (ref.get("soft_sigma_mm") or {}).items()}
    return {"held": refine_skeleton(*args, prior_weights=held, **kw),
            "prior_at_truth": refine_skeleton(*args, prior_weights=prior, soft=soft, **kw),
            "no_prior": refine_skeleton(*args, **kw)}


def case(args: tuple[str, int, int]) -> tuple[str, int, dict]:
    motion_name, seed, frames = args
    from mocapskel import evaluate, pipeline
    from mocapskel.stages import rigid
    from mocapskel.synth.presets import make, realistic

    take = make(realistic(seed=seed, frames=frames, motion=motion_name, markerset="cmu41"))
    clean = pipeline.run_until(take.markers, "clean").artifact
    joints = pipeline.run_until(evaluate.true_topology(take.truth, clean), "joints").artifact
    skel = pipeline.run_until(joints, "rigid", {"rigid": rigid.Params(uncertainty=False)}).artifact
    fit = pipeline.run_until(skel, "ik").artifact
    out = {"fit": evaluate.score_motion(fit, take.truth).joint_rms_mm}
    for name, res in refits(skel, fit, take.truth, clean.points).items():
        mot = pipeline.run_until(replace(skel, origin=res.origin, marker_local=res.marker_local), "ik").artifact
        out[name] = evaluate.score_motion(mot, take.truth).joint_rms_mm
    return motion_name, seed, out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4, 5, 6])
    ap.add_argument("--motions", nargs="+", default=list(MOTIONS))
    ap.add_argument("--frames", type=int, default=600)
    ap.add_argument("--procs", type=int, default=2)
    a = ap.parse_args()
    cases = [(m, s, a.frames) for m in a.motions for s in a.seeds]
    with get_context("fork").Pool(a.procs) as pool:
        got = {(m, s): o for m, s, o in pool.imap_unordered(case, cases)}
    halves = [("tuning", [s for s in a.seeds if s <= 3]), ("checking", [s for s in a.seeds if s > 3])]
    halves = [(h, ss) for h, ss in halves if ss]
    rows = []
    for m in a.motions:
        row = [m]
        for col in COLUMNS:
            row.append(" / ".join(f"{np.mean([got[(m, s)][col] for s in ss]):.1f}" for _, ss in halves))
        rows.append(row)
    print(f"Mean joint rms after IK (mm), seeds {' / '.join(','.join(map(str, ss)) for _, ss in halves)}:\n")
    print(table(["motion", "the fit", "joints held at the truth", "the prior's mean at the truth", "no prior"], rows))


if __name__ == "__main__":
    main()
