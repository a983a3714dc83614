"""The bundle adjustment's skin terms (``refine_skeleton(skin=...)``): their normal equations against a dense
finite-difference Jacobian, and what they do to a joint whose turns are small."""
from __future__ import annotations

import numpy as np

from mocapskel import pipeline
from mocapskel.solvers.model.calibrate import _exp, _Problem, _skin_matrices
from mocapskel.synth.chains import hang_chain


def test_normal_equations_with_skin_terms_match_a_dense_finite_difference_jacobian():
    take = hang_chain((3, 2, 3), 60, rng=np.random.default_rng(4), link_length=300.0, noise=0.3)
    skel = pipeline.run_until(take.markers, "rigid", {}).artifact
    pts = skel.joints.topology.segments.markers.points[skel.pose_frames]
    keep = np.arange(0, pts.shape[0], 25)[:4]
    p, R, l = skel.pose_root[keep], skel.pose_rot[keep], skel.marker_local
    kids = [c for c in range(len(skel.parent)) if skel.parent[c] >= 0]
    # the skin matrices from the whole refinement's rotations, then the four frames' rows of them
    extra = [(c, _skin_matrices(skel.pose_rot, int(skel.parent[c]), c)[keep]) for c in kids]
    pr = _Problem(skel.parent, skel.marker_segment, pts[keep], extra)
    S, F, nf, ng = pr.S, len(keep), pr.nf, pr.ng
    d = np.zeros((S + len(extra), 3))
    for c in pr.kids:
        d[c] = skel.origin[c] - skel.origin[skel.parent[c]]
    d[S:] = np.random.default_rng(2).normal(scale=30.0, size=(len(extra), 3))  # skin terms away from 0

    def unpack(g):
        d1, l1 = d.copy(), l.copy()
        for c in pr.kids:
            d1[c] += g[pr.gi[c] : pr.gi[c] + 3]
        for e, ge in enumerate(pr.ge):
            d1[S + e] += g[ge : ge + 3]
        for m in pr.used:
            l1[m] += g[pr.gl[int(m)] : pr.gl[int(m)] + 3]
        return d1, l1

    def residual(x):
        pose, g = x[: F * nf].reshape(F, nf), x[F * nf :]
        return pr.residual(p + pose[:, :3], _exp(pose[:, 3:].reshape(F, S, 3)) @ R, *unpack(g)).ravel()

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
        scale = np.abs(Jf.T @ Jf).max()
        assert np.allclose(Hff[f], Jf.T @ Jf, atol=1e-6 * scale)
        assert np.allclose(X[f, :, :ng], Jf.T @ Jg, atol=1e-6 * np.abs(Jf.T @ Jg).max())
        assert np.allclose(X[f, :, ng], Jf.T @ rf, atol=1e-6 * np.abs(Jf.T @ rf).max())
    Jg = J[:, F * nf :]
    assert np.allclose(Hgg, Jg.T @ Jg, atol=1e-6 * np.abs(Jg.T @ Jg).max())
    assert np.allclose(bg, Jg.T @ r0, atol=1e-6 * np.abs(Jg.T @ r0).max())
    # the skin terms' columns are not zero: they do enter the model
    assert np.abs(Jg[:, pr.ge[0] : pr.ge[-1] + 3]).max() > 1e-3
