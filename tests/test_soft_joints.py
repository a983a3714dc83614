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
    from mocapskel.solvers.model.joint_map import soft_joints

    for counts, soft in (((4, 3, 3), {1, 2}), ((3, 2, 3), set()), ((4, 3, 1), {1})):
        take = hang_chain(counts, 60, rng=np.random.default_rng(1), link_length=300.0, noise=0.3)
        skel = pipeline.run_until(take.markers, "rigid", {}).artifact
        n = np.bincount(skel.marker_segment, minlength=len(skel.names))
        got = soft_joints(skel, 2.0)
        assert set(got) == {c for c in range(len(skel.names)) if skel.parent[c] >= 0
                            and min(n[c], n[skel.parent[c]]) >= 3}, (counts, got)
        assert len(got) == len(soft) and set(got.values()) <= {2.0}


def test_the_reduced_matrix_with_soft_joints_eliminates_their_offsets_with_the_poses():
    """The uncertainty's curvature over the constant unknowns with soft joints: each frame's offsets eliminated with
    its pose, their prior in the frame's block, against a dense finite-difference Jacobian:
    ``Jg^T Jg - Jg^T Jp (Jp^T Jp + W)^-1 Jp^T Jg``, W the offsets' prior weights (the reference frame's rotations
    held, the root's origin fixed)."""
    from mocapskel.solvers.model import uncertainty as unc_mod

    take = hang_chain((3, 3, 3), 60, rng=np.random.default_rng(4), link_length=300.0, noise=0.3)
    skel = pipeline.run_until(take.markers, "rigid", {}).artifact
    pts = skel.joints.topology.segments.markers.points[skel.pose_frames]
    keep = np.arange(0, pts.shape[0], 25)[:4]
    soft = [c for c in range(len(skel.parent)) if skel.parent[c] >= 0]
    pr = _Problem(skel.parent, skel.marker_segment, pts[keep], soft, [0.05, 0.2][: len(soft)])
    S, F, nf, ng = pr.S, len(keep), pr.nf, pr.ng
    R, l, d = skel.pose_rot[keep], skel.marker_local, pr.offsets(skel.origin)
    p, _ = pr.soft_offsets(skel.pose_root[keep], R, d, l)
    lin = np.r_[0:3, 3 + 3 * S : nf]
    ref, fix_g = 1, unc_mod._gauge_fixed(pr)

    def residual(x):
        pose, g = x[: F * nf].reshape(F, nf), x[F * nf :]
        d1, l1 = _step(pr, d, l, g)
        return pr.residual(p + pose[:, lin], _exp(pose[:, 3 : 3 + 3 * S].reshape(F, S, 3)) @ R, d1, l1).ravel()

    n = F * nf + ng
    J = np.zeros((residual(np.zeros(n)).size, n))
    for i in range(n):
        e = np.zeros(n)
        e[i] = 1e-6
        J[:, i] = (residual(e) - residual(-e)) / 2e-6
    held = np.zeros(F * nf, dtype=bool)
    held[ref * nf + 3 : ref * nf + 3 + 3 * S] = True
    W = np.tile(np.r_[np.zeros(3 + 3 * S), pr.ws], F)[~held]
    Jp, Jg = J[:, : F * nf][:, ~held], J[:, F * nf :][:, ~fix_g]
    dense = Jg.T @ Jg - Jg.T @ Jp @ np.linalg.solve(Jp.T @ Jp + np.diag(W), Jp.T @ Jg)
    ours = unc_mod.reduced_normal_matrix(pr, p, R, d, l, ref, fix_g)[np.ix_(~fix_g, ~fix_g)]
    assert np.allclose(ours, dense, rtol=1e-5, atol=1e-6 * np.abs(dense).max())
    # the offsets the fit would have: with the frame's pose held, the markers' residual plus the prior is least
    r0 = residual(np.zeros(n))
    for f in range(F):
        Jo = J[:, f * nf + np.arange(3 + 3 * S, nf)]
        step = np.linalg.solve(Jo.T @ Jo + np.diag(pr.ws), -(Jo.T @ r0 + pr.ws * p[f, 3:]))
        assert np.abs(step).max() < 1e-6 * max(np.abs(p[f, 3:]).max(), 1.0), step  # already there


def test_soft_offsets_give_back_the_fits_marker_residual():
    """The offsets solved frame by frame at the fit's poses (:meth:`_Problem.soft_offsets`) reproduce the marker
    residual the fit ended with (its offsets are not kept)."""
    from mocapskel.solvers.model.calibrate import refine_skeleton

    take = hang_chain((3, 3, 3), 120, rng=np.random.default_rng(6), link_length=300.0, noise=0.5)
    skel = pipeline.run_until(take.markers, "rigid", {}).artifact
    pts = skel.joints.topology.segments.markers.points[skel.pose_frames]
    ref = int(np.searchsorted(skel.pose_frames, skel.rest_frame))
    soft = {c: 0.02 for c in range(len(skel.parent)) if skel.parent[c] >= 0}
    res = refine_skeleton(skel.parent, skel.origin, skel.marker_segment, skel.marker_local, pts, skel.pose_rot,
                          skel.pose_root, ref_frame=ref, iterations=40, soft=soft)
    pr = _Problem(skel.parent, skel.marker_segment, pts, sorted(soft), [soft[c] for c in sorted(soft)])
    p, eff = pr.soft_offsets(res.root_pos, res.rot, pr.offsets(res.origin), res.marker_local)
    rms = np.sqrt(pr.cost(p, res.rot, pr.offsets(res.origin), res.marker_local) / pr.w.sum())
    rigid_rms = np.sqrt(pr.cost(np.hstack([p[:, :3], 0 * p[:, 3:]]), res.rot, pr.offsets(res.origin),
                                res.marker_local) / pr.w.sum())
    assert abs(rms - res.rms[1]) < 1e-3 * res.rms[1], (rms, res.rms)
    assert rms < rigid_rms and 0 < eff < 3 * len(soft) * pts.shape[0]


def _wandering_chain(sigma: float, noise: float, frames: int = 800, seed: int = 0):
    """A root and two children of four markers each, turning at random; in every frame each child's joint sits off
    its fixed place by N(0, sigma^2) per axis (in its parent's frame), and every marker has noise N(0, noise^2)."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    parent = np.array([-1, 0, 1])
    origin = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -250.0], [0.0, 0.0, -500.0]])
    seg = np.repeat([0, 1, 2], 4)
    local = rng.normal(scale=60.0, size=(12, 3)) + np.repeat([[0, 0, 0], [0, 0, -120.0], [0, 0, -120.0]], 4, axis=0)
    rot = Rotation.from_rotvec(rng.normal(scale=0.6, size=(frames * 3, 3))).as_matrix().reshape(frames, 3, 3, 3)
    root = rng.normal(scale=300.0, size=(frames, 3))
    P = np.empty((frames, 3, 3))
    P[:, 0] = root
    for c in (1, 2):
        off = origin[c] - origin[c - 1] + rng.normal(scale=sigma, size=(frames, 3))
        P[:, c] = P[:, c - 1] + np.einsum("fij,fj->fi", rot[:, c - 1], off)
    x = P[:, seg] + np.einsum("fmij,mj->fmi", rot[:, seg], local) + rng.normal(scale=noise, size=(frames, 12, 3))
    return parent, origin, seg, local, x, rot, root


def test_how_far_joints_wander_comes_back_from_their_offsets_less_the_noise():
    """The slack's moments at the true skeleton and poses (``slack_moments``): the offsets' mean square less what the
    noise gives them is 3 sigma^2, joint by joint, for joints that wander by 2 mm and for joints fixed in place."""
    from mocapskel.solvers.model.slack import slack_moments

    for sigma in (2.0, 0.0):
        parent, origin, seg, local, x, rot, root = _wandering_chain(sigma, noise=1.0)
        e2, tr, n = slack_moments(parent, origin, seg, local, x, rot, root, [1, 2])
        assert (n == x.shape[0]).all()
        est = np.sqrt(np.maximum(0.0, (e2 - tr) / (3.0 * n)))  # noise 1 mm: sigma_n^2 = 1
        assert np.allclose(est, sigma, atol=0.15), (sigma, est)
        # the noise's share is what the offsets show when nothing wanders
        assert abs(e2.sum() / tr.sum() - (1.0 + 3.0 * sigma**2 * n.sum() / tr.sum())) < 0.1
