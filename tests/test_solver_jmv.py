"""Kirk's joint cost and the JMV joint solver."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mocapskel.solvers.joints.jmv import (
    BODY_MARKERS,
    algebraic_init,
    edge_alpha,
    fixed_radius_centres,
    jmv_joint,
    jmv_joint_long,
    nearest_midpoint,
)
from mocapskel.solvers.joints.cost import JointFit, balanced_alpha, joint_cost, joint_cost_grad
from mocapskel.solvers.grouping.pair_cost import pair_cost
from mocapskel.synth.chains import hang_chain


def rse(est: np.ndarray, truth: np.ndarray) -> float:
    """Hang (10): sqrt(sum of squared joint errors) / (joints x frames)."""
    F, M, _ = truth.shape
    return float(np.sqrt(np.sum((est - truth) ** 2)) / (M * F))


def groups(take):
    P, seg = take.markers.points, take.truth.marker_segment
    return [P[:, seg == s] for s in range(seg.max() + 1)]


def slow_cost(c, markers, alpha):
    """Kirk's Q written out marker by marker, frame by frame."""
    F, N, _ = markers.shape
    terms = []
    for m in range(N):
        ds = [np.linalg.norm(c[f] - markers[f, m]) for f in range(F)
              if np.isfinite(markers[f, m]).all() and np.isfinite(c[f]).all()]
        if not ds:
            continue
        dbar = sum(ds) / len(ds)
        var = sum((d - dbar) ** 2 for d in ds) / len(ds)
        terms.append(var + alpha * dbar)
    return sum(terms) / len(terms) if terms else np.inf


@settings(max_examples=40, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2**32 - 1), F=st.integers(1, 12), N=st.integers(1, 5),
       alpha=st.sampled_from([0.0, 0.01, 1.0]), gap=st.floats(0.0, 0.6))
def test_joint_cost_matches_slow_formula(seed, F, N, alpha, gap):
    rng = np.random.default_rng(seed)
    markers = rng.normal(size=(F, N, 3)) * 10
    markers[rng.random((F, N)) < gap] = np.nan
    c = rng.normal(size=(F, 3))
    c[rng.random(F) < gap / 3] = np.nan
    got = joint_cost(c, markers, alpha)
    want = slow_cost(c, markers, alpha)
    if np.isinf(want):
        assert np.isinf(got)
    else:
        assert got == pytest.approx(want, rel=1e-10, abs=1e-12)


def test_joint_cost_zero_at_true_joint():
    take = hang_chain([4, 3], 60, rng=np.random.default_rng(0))
    both = take.markers.points
    assert joint_cost(take.truth.joints[:, 0], both, 0.0) < 1e-25
    assert joint_cost(take.truth.joints[:, 0] + 0.1, both, 0.0) > 1e-4


def test_joint_cost_gradient_is_the_derivative():
    rng = np.random.default_rng(1)
    F, N = 7, 5
    markers = rng.normal(size=(F, N, 3))
    markers[2, 1] = np.nan
    c = rng.normal(size=(F, 3)) * 0.5
    for alpha in (0.0, 0.3):
        q, g = joint_cost_grad(c, markers, alpha)
        assert q == pytest.approx(joint_cost(c, markers, alpha), rel=1e-12)
        num = np.zeros_like(c)
        h = 1e-6
        for f in range(F):
            for i in range(3):
                cp, cm = c.copy(), c.copy()
                cp[f, i] += h
                cm[f, i] -= h
                num[f, i] = (joint_cost(cp, markers, alpha) - joint_cost(cm, markers, alpha)) / (2 * h)
        np.testing.assert_allclose(g, num, rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize("init", ["nearest", "auto", "algebraic"])
def test_jmv_alone_on_chain_433_beats_hang(init):
    # Hang's JMV rows: RSE 1e-2 .. 1e-3 on noise-free chains; ours converges to rounding.
    errs = []
    for seed in range(3):
        take = hang_chain([4, 3, 3], 100, rng=np.random.default_rng(seed))
        g = groups(take)
        est = np.stack([jmv_joint(g[e], g[e + 1], init=init).centre for e in range(2)], axis=1)
        errs.append(rse(est, take.truth.joints))
    assert np.mean(errs) < 1e-9


def test_jmv_two_markers_per_side_is_exact():
    # <2-2>: no basis anywhere; the four-point closed form starts JMV at the answer
    for seed in range(3):
        take = hang_chain([2, 2], 150, rng=np.random.default_rng(seed))
        a, b = groups(take)
        fit = jmv_joint(a, b)
        assert fit and fit.reason == ""
        assert np.abs(fit.centre - take.truth.joints[:, 0]).max() < 1e-8
        assert fit.cost < 1e-20


def test_jmv_long_fits_a_subsample_and_places_every_frame_exactly():
    # <2-2>, noise-free, 900 frames fitted on 150: the radii, then every frame from them
    take = hang_chain([2, 2], 900, rng=np.random.default_rng(5))
    a, b = groups(take)
    fit = jmv_joint_long(a, b, max_frames=150)
    assert fit and np.isfinite(fit.centre).all()
    assert np.abs(fit.centre - take.truth.joints[:, 0]).max() < 1e-7
    truth_r = np.linalg.norm(np.concatenate([a, b], axis=1) - take.truth.joints[:, :1], axis=-1).mean(0)
    np.testing.assert_allclose(fit.radii, truth_r, rtol=1e-9)
    # a short take is fitted whole
    short = jmv_joint_long(a[:100], b[:100], max_frames=150)
    np.testing.assert_allclose(short.centre, jmv_joint(a[:100], b[:100]).centre)


def test_fixed_radius_centres_from_a_rough_start():
    take = hang_chain([2, 2], 200, rng=np.random.default_rng(6), noise=0.002)
    a, b = groups(take)
    pts = np.concatenate([a, b], axis=1)
    truth = take.truth.joints[:, 0]
    r = np.linalg.norm(pts - truth[:, None], axis=-1).mean(0)
    start = truth + np.random.default_rng(0).normal(0, 0.05, truth.shape)  # 5 % of a link off
    c = fixed_radius_centres(pts, r, start)
    # each frame's least squares: a stationary point (the gradient of sum (d - r)^2 vanishes),
    # the same as a much tighter run's, and close to the truth
    d = np.linalg.norm(c[:, None] - pts, axis=-1)
    g = np.einsum("fm,fmi->fi", d - r, (c[:, None] - pts) / d[..., None])
    assert np.median(np.abs(g)) < 1e-9 and np.abs(g).max() < 1e-3
    tight = fixed_radius_centres(pts, r, start, iterations=500, tol=1e-14)
    cost = lambda x: ((np.linalg.norm(x[:, None] - pts, axis=-1) - r) ** 2).sum(1)  # noqa: E731
    assert np.all(cost(c) <= cost(tight) * (1 + 1e-3) + 1e-15)
    assert np.abs(c - tight).max() < 2e-3  # flat frames (four nearly coplanar points) end a little apart
    assert np.sqrt(np.mean(np.sum((c - truth) ** 2, -1))) < 0.02
    pts[3, :2] = np.nan  # two points left: no joint
    assert np.isnan(fixed_radius_centres(pts, r, start)[3]).all()


def test_algebraic_init_exact_for_four_points():
    take = hang_chain([2, 2], 80, rng=np.random.default_rng(11))
    a, b = groups(take)
    guess = algebraic_init(a, b)
    ok = np.isfinite(guess).all(-1)
    assert ok.mean() > 0.9
    np.testing.assert_allclose(guess[ok], take.truth.joints[ok, 0], atol=1e-8)
    assert algebraic_init(a[:, :1], b) is None  # three points: undetermined


def test_jmv_minimises_q_with_noise():
    take = hang_chain([4, 3], 200, rng=np.random.default_rng(2), noise=0.005)
    a, b = groups(take)
    both = np.concatenate([a, b], axis=1)
    fit = jmv_joint(a, b)
    assert fit.ok
    assert fit.cost <= joint_cost(take.truth.joints[:, 0], both) + 1e-15
    assert fit.cost == pytest.approx(joint_cost(fit.centre, both), rel=1e-12)
    # 7 markers, 0.5 % noise: joint error of the order of the noise
    err = np.sqrt(np.mean(np.sum((fit.centre - take.truth.joints[:, 0]) ** 2, -1)))
    assert err < 0.03
    q, g = joint_cost_grad(fit.centre, both)
    assert np.abs(g).max() < 1e-7  # a stationary point


def test_jmv_with_alpha_and_init_array():
    take = hang_chain([3, 3], 100, rng=np.random.default_rng(4))
    a, b = groups(take)
    truth = take.truth.joints[:, 0]
    fit = jmv_joint(a, b, alpha=0.0, init=truth + 0.05)
    assert np.abs(fit.centre - truth).max() < 1e-9
    # alpha pulls the joint towards the markers: a small bias, lower mean distance
    fa = jmv_joint(a, b, alpha=0.05)
    assert fa.ok
    both = np.concatenate([a, b], 1)
    assert fa.cost <= joint_cost(truth, both, 0.05) + 1e-12
    dist = lambda c: np.nanmean(np.linalg.norm(both - c[:, None], axis=-1))  # noqa: E731
    assert dist(fa.centre) < dist(truth)


def test_jmv_with_gaps():
    take = hang_chain([4, 3], 120, rng=np.random.default_rng(5))
    a, b = groups(take)
    a, b = a.copy(), b.copy()
    a[10:30, 0] = np.nan
    b[50:70, 1:] = np.nan
    a[80:90] = np.nan  # frames 80-89: only group b's three markers
    b[80:85] = np.nan  # frames 80-84: nothing at all
    fit = jmv_joint(a, b)
    truth = take.truth.joints[:, 0]
    assert np.isnan(fit.centre[80:85]).all()
    seen = np.isfinite(fit.centre).all(-1)
    assert seen.sum() == 115
    good = seen.copy()
    good[85:90] = False  # 3 points of one rigid group: the joint is not determined there
    assert np.abs(fit.centre[good] - truth[good]).max() < 1e-8


def test_jmv_failures_are_values():
    F = 20
    rng = np.random.default_rng(0)
    a = rng.normal(size=(F, 2, 3))
    fit = jmv_joint(a, np.zeros((F, 0, 3)))
    assert isinstance(fit, JointFit) and not fit and "no markers" in fit.reason
    fit = jmv_joint(a[:, :1], a[:, 1:])
    assert not fit and "3 markers" in fit.reason and np.isnan(fit.centre).all()
    assert np.isinf(fit.cost)
    with pytest.raises(ValueError):
        jmv_joint(a, a, init="bogus")
    fit = jmv_joint(a, a[:, :1], init="mtb")
    assert not fit and "mtb" in fit.reason


def test_nearest_midpoint():
    a = np.zeros((3, 2, 3))
    a[:, 1] = [10.0, 0, 0]
    b = np.zeros((3, 1, 3))
    b[:, 0] = [12.0, 0, 0]
    np.testing.assert_allclose(nearest_midpoint(a, b), [[11.0, 0, 0]] * 3)


def test_pair_cost_prefers_true_joints():
    for counts in ([4, 3, 3, 4], [2, 2, 1, 2], [3, 2, 3]):
        take = hang_chain(counts, 400, rng=np.random.default_rng(8), noise=0.002)
        g = groups(take)
        L = len(g)
        C = np.full((L, L), np.inf)
        for i in range(L):
            for j in range(i + 1, L):
                C[i, j] = C[j, i] = pair_cost(g[i], g[j], alpha=0.01, frames=40)
        for i in range(L):
            # each segment's cheapest partner is a chain neighbour
            assert abs(int(np.argmin(C[i])) - i) == 1
        assert np.isfinite(C[~np.eye(L, dtype=bool)]).all()
    assert np.isinf(pair_cost(g[0], np.zeros((400, 0, 3)), alpha=0.01))
    assert np.isfinite(pair_cost(g[0], g[1], alpha=0.01, frames=np.arange(0, 400, 7)))


def test_adjugate_is_the_cross_products_of_rows_bit_for_bit():
    """The 3x3 adjugates JMV's damped steps invert with: each column the cross product of the other
    two rows (``A adj(A) = det(A) I``), the same floating-point result as three cross products, in
    the same memory layout (a transposed one changed a real take's pair costs by up to 3.6 mm^2)."""
    from mocapskel.solvers.joints.jmv import _adj3
    from mocapskel.solvers.joints.cost import _cross

    rng = np.random.default_rng(0)
    for F in (0, 1, 7, 300):
        A = rng.normal(size=(F, 3, 3)) * 10.0 ** rng.integers(-5, 5, size=(F, 1, 1))
        ref = np.stack([_cross(A[:, 1], A[:, 2]), _cross(A[:, 2], A[:, 0]), _cross(A[:, 0], A[:, 1])], axis=2)
        assert np.array_equal(_adj3(A), ref)
        assert _adj3(A).flags["C_CONTIGUOUS"]  # the layout of the products that follow, and so their last bits
        if F:
            scale = np.abs(A).max(axis=(1, 2)) ** 3
            err = np.abs(A @ _adj3(A) - np.linalg.det(A)[:, None, None] * np.eye(3)).max(axis=(1, 2))
            assert (err <= 1e-12 * scale).all()


def test_edge_alpha_puts_a_bodys_share_on_its_marker_nearest_a_two_marker_limb():
    """Between a body of four markers and a limb segment of two, the body's half of Kirk's penalty goes to
    the body's marker nearest the limb (mean over frames, a marker's gaps left out); the limb keeps its half,
    the total is Kirk's. Between segments of other sizes (a three-marker plate and two, four and one, two and
    two) and with no penalty, the balanced weights stay."""
    rng = np.random.default_rng(5)
    F = 40
    body = rng.normal(0.0, 100.0, (F, BODY_MARKERS, 3))
    limb = rng.normal(0.0, 100.0, (F, 2, 3))
    body[:, 2] = limb.mean(1) + rng.normal(0.0, 20.0, (F, 3))  # the body's marker nearest the limb
    body[::3, 2] = np.nan  # unseen now and then
    w = np.asarray(edge_alpha(0.3, body, limb))
    bal = np.asarray(balanced_alpha(0.3, BODY_MARKERS, 2))
    assert w.shape == (BODY_MARKERS + 2,)
    assert np.allclose(w[:BODY_MARKERS], [0.0, 0.0, bal[:BODY_MARKERS].sum(), 0.0])
    assert np.allclose(w[BODY_MARKERS:], bal[BODY_MARKERS:]) and np.isclose(w.sum(), bal.sum())
    # the body given second: the same weights in its place
    w2 = np.asarray(edge_alpha(0.3, limb, body))
    assert np.allclose(w2, np.concatenate([w[BODY_MARKERS:], w[:BODY_MARKERS]]))
    for a, b in ((body[:, :3], limb), (body, limb[:, :1]), (limb, limb + 50.0)):
        assert np.allclose(edge_alpha(0.3, a, b), balanced_alpha(0.3, a.shape[1], b.shape[1]))
    assert edge_alpha(0.0, body, limb) == 0.0
