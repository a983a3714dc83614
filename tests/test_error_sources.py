"""``bench.error_sources``: its refits start at the true joints. On a generated walk whose markers ride on rigid
segments (1 mm noise, no skin motion), the joints held there and posed by IK are within a few millimetres of the
truth, and the fit's own error is what the bench compares them with."""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from bench.error_sources import refits
from mocapskel import evaluate, pipeline
from mocapskel.stages import rigid
from mocapskel.synth.presets import Recipe, make


def test_the_refits_start_at_the_true_joints():
    take = make(Recipe(kind="human", seed=2, frames=600, motion="walk", noise_mm=1.0))
    clean = pipeline.run_until(take.markers, "clean").artifact
    joints = pipeline.run_until(evaluate.true_topology(take.truth, clean), "joints").artifact
    skel = pipeline.run_until(joints, "rigid", {"rigid": rigid.Params(uncertainty=False)}).artifact
    fit = pipeline.run_until(skel, "ik").artifact
    got = refits(skel, fit, take.truth, clean.points)
    held = pipeline.run_until(replace(skel, origin=got["held"].origin, marker_local=got["held"].marker_local),
                              "ik").artifact
    sc = evaluate.score_motion(held, take.truth)
    assert len(sc.joint_rms_each) == 14
    # the joints where the truth has them: what IK leaves of 1 mm noise (measured 1.21 mm, the worst joint 1.9; the
    # fit itself 4.7, its left wrist 12.3 and left ankle 9.7)
    assert sc.joint_rms_mm < 2.0, sc.joint_rms_each
    assert max(sc.joint_rms_each.values()) < 3.0, sc.joint_rms_each
    assert np.isfinite(got["prior_at_truth"].origin).all() and np.isfinite(got["no_prior"].origin).all()
