"""Property-based tests (hypothesis) of the numerical kernels on points that cannot be solved.

Two rigid bodies joined at a ball joint, moved at random, then spoilt: a body's markers in one line
or on one spot, the whole take far from the origin (up to 1e5 mm, where squares of coordinates
cancel), a tiny body, points missing at random, whole frames missing. Every kernel that takes points
(the rigid fits, generalised Procrustes, the IK's segment poses, the sphere fits, SCoRE, JMV, MTB,
the segment stage's frame tests and distance stds) must answer with a value (NaN where a frame cannot
be solved, a falsy or flagged result where nothing can) or raise the project's ``DataError``:
never a LinAlgError, ValueError or ZeroDivisionError, never a RuntimeWarning, never an infinity.
"""
from __future__ import annotations

import os
import warnings

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mocapskel.errors import DataError
from mocapskel.solvers import rigid, rigid_shape
from mocapskel.solvers.joints import hybrid, jmv, mtb, score
from mocapskel.solvers.grouping import distances, grouping, partition
from mocapskel.solvers.spheres import sphere
from mocapskel.solvers.spheres.mle import sphere_mle
from mocapskel.solvers.ik.segment_poses import segment_poses
from mocapskel.synth.rotations import rotvec_to_matrix

#: MOCAPSKEL_HYPOTHESIS_SCALE=20 runs 20 times as many examples (a longer hunt; the suite uses 1).
SCALE = max(1, int(os.environ.get("MOCAPSKEL_HYPOTHESIS_SCALE", "1")))
#: The suite draws the same examples every run (a CI run is reproducible); a longer hunt draws at random.
RANDOM = SCALE > 1
COMMON = settings(max_examples=60 * SCALE, deadline=None, derandomize=not RANDOM,
                  suppress_health_check=[HealthCheck.too_slow])

SPOILS = ("none", "collinear", "coincident", "one_spot", "two_points", "tiny")


@st.composite
def two_bodies(draw) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(A (F, Na, 3), B (F, Nb, 3), joint (F, 3)): two bodies on a ball joint, spoilt as drawn."""
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    F = draw(st.integers(1, 40))
    na, nb = (draw(st.integers(1, 6) | st.sampled_from([21, 52])) for _ in "ab")  # > 20, > 50: other paths
    size = draw(st.sampled_from([100.0, 1e-3]))
    shapes = []
    for n in (na, nb):
        s = rng.normal(0.0, size, (n, 3))
        spoil = draw(st.sampled_from(SPOILS))
        if spoil == "collinear":
            s = rng.normal(0.0, size, n)[:, None] * rng.normal(size=3)
        elif spoil == "coincident" and n > 1:
            s[1:] = s[0]
        elif spoil == "one_spot":
            s[:] = 0.0
        elif spoil == "two_points":
            s = s[np.minimum(np.arange(n), 1)]
        elif spoil == "tiny":
            s *= 1e-9
        shapes.append(s)
    still = draw(st.booleans())
    turn = 0.0 if still else draw(st.sampled_from([1e-6, 0.3, 2.0]))
    Ra = rotvec_to_matrix(turn * rng.normal(size=(F, 3)))
    Rb = rotvec_to_matrix(turn * rng.normal(size=(F, 3)))
    direction = rng.normal(size=3)
    offset = draw(st.sampled_from([0.0, 6700.0, 1e5])) * direction / np.linalg.norm(direction)
    travel = draw(st.sampled_from([0.0, 12000.0]))
    root = offset + np.linspace(0.0, travel, F)[:, None] * np.array([1.0, 0.0, 0.0])
    joint = root + np.einsum("fij,j->fi", Ra, np.array([0.0, 0.0, -size]))
    A = root[:, None] + np.einsum("fij,nj->fni", Ra, shapes[0])
    B = joint[:, None] + np.einsum("fij,nj->fni", Rb, shapes[1] - [0.0, 0.0, size])
    noise = draw(st.sampled_from([0.0, 1.0]))
    A += rng.normal(0.0, noise, A.shape)
    B += rng.normal(0.0, noise, B.shape)
    first = draw(st.sampled_from(["as is", "in line", "on one spot", "two on one"]))
    for X in (A, B):  # the first frame spoilt alone (a body seen edge-on, two labels on one point)
        if first == "in line":
            X[0] = X[0, 0] + np.outer(rng.normal(size=X.shape[1]), X[0, -1] - X[0, 0])
        elif first == "on one spot":
            X[0] = X[0, 0]
        elif first == "two on one" and X.shape[1] > 1:
            X[0, 1] = X[0, 0]
    gone = draw(st.sampled_from([0.0, 0.2, 0.7, 1.0]))
    for X in (A, B):
        X[rng.random(X.shape[:2]) < gone] = np.nan
    if draw(st.booleans()):
        A[: F // 2] = np.nan  # whole frames unseen
    return A, B, joint


def _values(out) -> list[np.ndarray]:
    """The float arrays in a kernel's answer (tuples and result objects opened)."""
    if isinstance(out, np.ndarray):
        return [out] if out.dtype.kind == "f" else []
    if isinstance(out, (float, np.floating)):
        return [np.asarray(out)]
    if isinstance(out, (tuple, list)):
        return [v for x in out for v in _values(x)]
    if hasattr(out, "__dataclass_fields__"):  # a fit's cost is inf where nothing was fitted (documented)
        return [v for k in out.__dataclass_fields__ if k != "cost" for v in _values(getattr(out, k))]
    return []


def _out_of_line(X: np.ndarray, complete: bool = False) -> bool:
    """Whether some frame of X (F, N, 3) sees three or more points (all of them, if ``complete``) clearly
    out of one line (second singular value of the centred points over a thousandth of the first)."""
    for x in X:
        x = x[np.isfinite(x).all(1)]
        if len(x) >= 3 and (not complete or len(x) == X.shape[1]):
            sv = np.linalg.svd(x - x.mean(0), compute_uv=False)
            if sv[1] > 1e-3 * sv[0]:
                return True
    return False


def _answers(kernel, *args, **kw):
    """Call a kernel with every RuntimeWarning an error; it answers with a value (no infinity in it) or
    raises DataError."""
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        with np.errstate(divide="warn", over="warn", invalid="warn", under="ignore"):  # numpy's defaults
            try:
                out = kernel(*args, **kw)
            except DataError:
                return None
    for v in _values(out):
        assert not np.isinf(v).any(), f"{kernel.__name__} answered an infinity"
    return out


@COMMON
@given(two_bodies())
def test_rigid_fits_answer(data) -> None:
    A, B, _ = data
    ref = A[np.argmax(np.isfinite(A).all(-1).sum(1))]
    R, t, rms = _answers(rigid.kabsch, ref, A)
    assert np.isfinite(R).all(axis=(1, 2)).sum() == np.isfinite(t).all(1).sum()
    _answers(rigid_shape.shape_poses, ref, A)
    _answers(rigid_shape.procrustes_shape, np.concatenate([A, B], 1))
    shape = _answers(rigid_shape.procrustes_shape, A, 0)[0]
    # a shape whenever some frame can be aligned, whichever frame is asked for (a frame whose points lie
    # in one line used to leave it all NaN)
    assert np.isfinite(shape).any() or not _out_of_line(A)
    AB = np.concatenate([A, B], 1)
    cols = [np.arange(A.shape[1]), A.shape[1] + np.arange(B.shape[1])]
    _answers(segment_poses, [ref, B[np.argmax(np.isfinite(B).all(-1).sum(1))]], cols, AB)


@COMMON
@given(two_bodies())
def test_sphere_fits_answer(data) -> None:
    A, B, _ = data
    # B's markers in A's frame lie on spheres about the joint
    ref = A[np.argmax(np.isfinite(A).all(-1).sum(1))]
    R, t = rigid_shape.shape_poses(ref, A)
    local = np.einsum("fji,fnj->fni", R, B - t[:, None])
    for fit in (sphere.gdke, sphere.ugdk, sphere.sphere_lls):
        _answers(fit, local[:, 0])
    _answers(sphere.sphere_lls, local[:, 0], solver="lstsq")
    _answers(sphere.mgdk, local)
    _answers(sphere.mgdk, local, 0.0)
    _answers(sphere.ugdk, local[:, 0], 1.0)
    inc = sphere.IGDK(local.shape[1])
    inc.update(local)
    _answers(inc.result)
    if len(local) <= 12:  # the iterative reference fit: a few small ones
        _answers(sphere_mle, local, max_nfev=20)


@COMMON
@given(two_bodies())
def test_score_answers(data) -> None:
    A, B, _ = data
    fit = _answers(score.score_from_markers, A, B)
    assert fit is None or fit.ok or fit.reason
    ra, rb = (X[np.argmax(np.isfinite(X).all(-1).sum(1))] for X in (A, B))
    R1, t1, _ = rigid.kabsch(ra, A)
    R2, t2, _ = rigid.kabsch(rb, B)
    _answers(score.score, R1, t1, R2, t2)
    _answers(score.sara, R1, t1, R2, t2)
    _answers(score.score_hinge, R1, t1, R2, t2, ra, rb)
    if _out_of_line(A, complete=True) and _out_of_line(B, complete=True):
        assert "collinear" not in fit.reason  # a frame in line is no reference while another is not


@COMMON
@given(two_bodies())
def test_jmv_and_mtb_answer(data) -> None:
    A, B, _ = data
    A, B = A[:, :8], B[:, :8]  # joints are fitted to a few markers a segment (the four-point start tries them all)
    _answers(jmv.jmv_joint, A, B, max_iter=10)
    _answers(jmv.jmv_joint_long, A, B, max_iter=10, max_frames=8)
    basis = _answers(mtb.mtb_basis, A)
    if basis:
        _answers(mtb.mtb_joint, basis, A, B, max_iter=10)
        _answers(mtb.mtb_joint, basis, A, B, max_iter=10, basis_side="a")
    _answers(jmv.algebraic_init, A, B)
    _answers(jmv.nearest_midpoint, A, B)
    P = np.concatenate([A, B], 1)
    start = np.nan_to_num(P).mean(1)
    _answers(jmv.fixed_radius_centres, P, np.full(P.shape[1], 50.0), start, iterations=10)
    _answers(hybrid.solve_tree, [A, B], np.array([[0, 1]]), jmv_kwargs={"max_iter": 10})


@COMMON
@given(two_bodies())
def test_segment_frame_tests_answer(data) -> None:
    A, B, _ = data
    P = np.concatenate([A, B], 1)
    M = P.shape[1]
    for idx in (np.arange(A.shape[1]), np.arange(M)):
        if idx.size >= 3:
            _answers(partition.frame_scatters, P, idx, 150, 2)
    std, _ = _answers(distances.distance_std, P)
    _answers(distances.skin_level, std)
    _answers(distances.computed_points, std, 0.05)
    _answers(distances.choose_sigma, std, None, None)
    _answers(distances.rigid_groups, std, 1.0)
    _answers(distances.average_linkage_heights, np.nan_to_num(std, nan=1e3))
    seen = P[np.isfinite(P).all(axis=(1, 2))]
    if len(seen) and M >= 3:
        _answers(partition.rigid_rms, seen)
        _answers(partition.scatter_in_frame, seen, np.arange(3))
        _answers(partition.best_split, seen, np.random.default_rng(0), 2)
    if M >= 4:
        _answers(grouping.turns_about_a_point, P, M - 1, np.arange(M - 1), 1.0)


@settings(max_examples=10 * SCALE, deadline=None, derandomize=not RANDOM)
@given(st.integers(0, 2**32 - 1), st.sampled_from([1.0, 30.0, 150.0]))
def test_far_from_the_origin_the_kernels_give_what_they_give_near_it(seed: int, size: float) -> None:
    """The same motion near the origin and 1e5 mm from it: poses, shapes and joints move with it, to within
    1e-7 of the bodies' size (the kernels work on coordinates centred on the data, not on squares of raw
    coordinates, which would cancel there)."""
    rng = np.random.default_rng(seed)
    F = 120
    sa, sb = rng.normal(0.0, size, (4, 3)), rng.normal(0.0, size, (3, 3)) - [0.0, 0.0, 3.0 * size]
    root = np.cumsum(rng.normal(0.0, 0.05 * size, (F, 3)), 0)
    A0 = root[:, None] + np.einsum("fij,nj->fni", rotvec_to_matrix(rng.normal(0.0, 0.5, (F, 3))), sa)
    B0 = root[:, None] + np.einsum("fij,nj->fni", rotvec_to_matrix(rng.normal(0.0, 0.8, (F, 3))), sb)
    B0 += rng.normal(0.0, 0.01 * size, B0.shape)

    def answers(o: np.ndarray) -> dict[str, np.ndarray]:
        A, B = A0 + o, B0 + o
        R, t, _ = rigid.kabsch(A0[0], A)
        local = np.einsum("fji,fnj->fni", R, B - t[:, None])
        Rs, ts = segment_poses([A0[0], B0[0]], [np.arange(4), 4 + np.arange(3)], np.concatenate([A, B], 1))
        return {
            "kabsch": np.concatenate([R.reshape(F, -1) * size, t - o], 1),
            "shape_poses": rigid_shape.shape_poses(A0[0], A)[1] - o,
            "segment_poses": np.concatenate([Rs.reshape(F, -1) * size, ts.reshape(F, -1) - np.tile(o, 2)], 1),
            "procrustes": rigid_shape.procrustes_shape(A, 0)[0] - o,
            "mgdk": sphere.mgdk(local, 0.0).centre,
            "score": score.score_from_markers(A, B).c1,
            "jmv": jmv.jmv_joint(A[:40], B[:40], max_iter=20).centre - o,
            "mtb": mtb.mtb_joint(mtb.mtb_basis(A), A, B).centre - o,
            "frame test": partition.frame_scatters(np.concatenate([A, B], 1), np.arange(4), 150, 20)[0],
        }

    near, far = answers(np.zeros(3)), answers(rng.normal(size=3) / np.sqrt(3) * 1e5)
    for k in near:  # NaN in the same places (a group in line has no frame), the rest alike
        assert np.isfinite(near[k]).any() or k == "frame test", k
        np.testing.assert_allclose(far[k], near[k], rtol=0, atol=1e-7 * size, err_msg=k)


def test_the_geometric_sphere_fit_of_samples_on_one_spot_is_a_failed_fit() -> None:
    """Five samples of one point: the fit ends on them (radius 0) and says it failed; the centre's
    information took the direction of a sample on the centre itself, 0 / 0 (a RuntimeWarning)."""
    fit = _answers(sphere_mle, np.full((5, 3), 1e5))
    assert not fit and fit.reason
