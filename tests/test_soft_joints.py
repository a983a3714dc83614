"""Soft joints in the bundle adjustment (``refine_skeleton(soft=...)``): each frame's offset of a joint from its
fixed place, its normal equations against a dense finite-difference Jacobian."""
from __future__ import annotations

import numpy as np

from mocapskel import pipeline
from mocapskel.solvers.model.calibrate import _exp, _Problem, _step
from mocapskel.synth.chains import hang_chain


def test_normal_equations_with_soft_joints_match_a_dense_finite_difference_jacobian():
    take = hang_chain((3, 2, 3), 60, rng=np.random.default_rng(4), link_length=300.0, noise=0.3)
    skel = pipeline.run_until(take.markers, "rigid", {}).artifact
    pts = skel.joints.topology.segments.markers.points[skel.pose_frames]
    keep = np.arange(0, pts.shape[0], 25)[:4]
    R, l = skel.pose_rot[keep], skel.marker_local
    soft = [c for c in range(len(skel.parent)) if skel.parent[c] >= 0]
    pr = _Problem(skel.parent, skel.marker_segment, pts[keep], soft)
    S, F, nf, ng = pr.S, len(keep), pr.nf, pr.ng
    assert nf == 3 + 3 * S + 3 * len(soft)
    # the root's origin, then each soft joint's offset, away from 0
    p = np.hstack([skel.pose_root[keep], np.random.default_rng(2).normal(scale=20.0, size=(F, 3 * len(soft)))])
    d = pr.offsets(skel.origin)
    lin = np.r_[0:3, 3 + 3 * S : nf]  # a frame's pose unknowns that add to p

    def residual(x):
        pose, g = x[: F * nf].reshape(F, nf), x[F * nf :]
        d1, l1 = _step(pr, d, l, g)
        return pr.residual(p + pose[:, lin], _exp(pose[:, 3 : 3 + 3 * S].reshape(F, S, 3)) @ R, d1, l1).ravel()

    n = F * nf + ng
    r0 = residual(np.zeros(n))
    J = np.zeros((r0.size, n))
    for i in range(n):
        e = np.zeros(n)
        e[i] = 1e-6
        J[:, i] = (residual(e) - residual(-e)) / 2e-6
    Hff, X, Hgg, bg = pr.normal_equations(slice(None), p, R, d, l)
    rows = r0.size // F
    for f in range(F):
        Jf = J[f * rows : (f + 1) * rows, f * nf : (f + 1) * nf]
        Jg = J[f * rows : (f + 1) * rows, F * nf :]
        rf = r0[f * rows : (f + 1) * rows]
        assert np.allclose(Hff[f], Jf.T @ Jf, atol=1e-6 * np.abs(Jf.T @ Jf).max())
        assert np.allclose(X[f, :, :ng], Jf.T @ Jg, atol=1e-6 * np.abs(Jf.T @ Jg).max())
        assert np.allclose(X[f, :, ng], Jf.T @ rf, atol=1e-6 * np.abs(Jf.T @ rf).max())
        assert np.abs(Jf[:, 3 + 3 * S :]).max() > 0.5  # the soft offsets do move markers
    Jg = J[:, F * nf :]
    assert np.allclose(Hgg, Jg.T @ Jg, atol=1e-6 * np.abs(Jg.T @ Jg).max())
    assert np.allclose(bg, Jg.T @ r0, atol=1e-6 * np.abs(Jg.T @ r0).max())


def test_only_joints_between_segments_with_poses_of_their_own_are_soft():
    """A segment of one or two markers is posed through its joints, so its joints stay rigid."""
    from mocapskel.solvers.model.joint_map import _soft_joints

    for counts, soft in (((4, 3, 3), {1, 2}), ((3, 2, 3), set()), ((4, 3, 1), {1})):
        take = hang_chain(counts, 60, rng=np.random.default_rng(1), link_length=300.0, noise=0.3)
        skel = pipeline.run_until(take.markers, "rigid", {}).artifact
        n = np.bincount(skel.marker_segment, minlength=len(skel.names))
        got = _soft_joints(skel, 2.0)
        assert set(got) == {c for c in range(len(skel.names)) if skel.parent[c] >= 0
                            and min(n[c], n[skel.parent[c]]) >= 3}, (counts, got)
        assert len(got) == len(soft) and set(got.values()) <= {2.0}
