"""Tests of the sphere fits (Knight & Semwal 2009): GDKE, UGDK, MGDK, IGDK, LLS, MLE, CRLB."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mocapskel.solvers.spheres.sphere import (
    IGDK,
    gdke,
    mgdk,
    sphere_lls,
    ugdk,
)
from mocapskel.solvers.spheres.mle import sphere_crlb, sphere_mle
from mocapskel.solvers.spheres.solve import SphereFit

CENTRE = np.array([1200.0, -350.0, 900.0])  # lab-like coordinates, mm


def _cap(rng: np.random.Generator, n: int, half_angle_deg: float, axis: np.ndarray | None = None) -> np.ndarray:
    """n unit directions uniform (by area) on the cap of the given half-angle around axis (default +z)."""
    z = rng.uniform(np.cos(np.radians(half_angle_deg)), 1.0, n)
    phi = rng.uniform(0, 2 * np.pi, n)
    s = np.sqrt(1 - z * z)
    u = np.column_stack([s * np.cos(phi), s * np.sin(phi), z])
    if axis is None:
        return u
    rot, _ = Rotation.align_vectors([axis], [[0.0, 0.0, 1.0]])
    return rot.apply(u)


def _methods_single():
    return {
        "gdke": gdke,
        "ugdk-estimated": ugdk,
        "ugdk-zero": lambda X: ugdk(X, 0.0),
        "mgdk": mgdk,
        "lls": sphere_lls,
        "lls-lstsq": lambda X: sphere_lls(X, solver="lstsq"),
        "mle": sphere_mle,
        "igdk": lambda X: IGDK().update(X[:100]).update(X[100:]).result(),
        "igdk-estimated": lambda X: IGDK().update(X[:100]).update(X[100:]).result(None),
    }


# ---------------------------------------------------------------- exact data


@pytest.mark.parametrize("name", list(_methods_single()))
@pytest.mark.parametrize("half_angle", [180.0, 40.0])
def test_exact_samples_give_exact_centre(name, half_angle):
    rng = np.random.default_rng(1)
    r = 250.0
    X = CENTRE + r * _cap(rng, 500, half_angle, axis=np.array([0.3, -1.0, 0.4]))
    fit = _methods_single()[name](X)
    assert isinstance(fit, SphereFit)
    assert fit.ok and fit, fit.reason
    np.testing.assert_allclose(fit.centre, CENTRE, rtol=0, atol=1e-9)
    assert abs(fit.radius - r) < 1e-9
    assert fit.n == 500
    assert fit.rms < 1e-5  # moments-based rms has a rounding floor near 1e-8 r
    if name.endswith("estimated"):
        assert fit.sigma < 1e-5


def test_exact_multi_radius_centre():
    rng = np.random.default_rng(2)
    radii = np.array([80.0, 210.0, 330.0])
    U = np.stack([_cap(rng, 400, 60.0) for _ in radii], axis=1)  # (N, K, 3)
    X = CENTRE + radii[None, :, None] * U
    for fit in (mgdk(X), mgdk(X, 0.0), sphere_mle(X), IGDK().update(X).result(), mgdk(list(X.transpose(1, 0, 2)))):
        assert fit.ok, fit.reason
        np.testing.assert_allclose(fit.centre, CENTRE, rtol=0, atol=1e-9)
        np.testing.assert_allclose(fit.radii, radii, rtol=0, atol=1e-9)
        assert np.isnan(fit.radius)  # several markers: use radii


# ---------------------------------------------------------------- bias (statistics)


def _bias_table(half_angle: float, sigma: float, sizes=(1_000, 10_000, 100_000), seeds: int = 16):
    """Mean centre error vector (bias), its standard error, over seeds, for GDKE and UGDK."""
    c0 = np.array([0.3, -0.2, 0.1])
    out = {}
    for n in sizes:
        err = {"gdke": [], "ugdk": []}
        sig = []
        for seed in range(seeds):
            rng = np.random.default_rng([seed, n, int(half_angle)])
            X = c0 + _cap(rng, n, half_angle) + rng.normal(0, sigma, (n, 3))
            err["gdke"].append(gdke(X).centre - c0)
            u = ugdk(X)
            assert u.ok, u.reason
            err["ugdk"].append(u.centre - c0)
            sig.append(u.sigma)
        for k, e in err.items():
            e = np.asarray(e)
            out[k, n] = (np.linalg.norm(e.mean(0)), np.linalg.norm(e.std(0, ddof=1) / np.sqrt(seeds)))
        out["sigma", n] = float(np.mean(sig))
    return out


@pytest.mark.parametrize("half_angle,sigma", [(90.0, 0.05), (30.0, 0.02)])
def test_ugdk_bias_vanishes_while_gdke_bias_stays(half_angle, sigma):
    # unit sphere; sigma relative to the radius. Noise makes GDKE pull the
    # centre towards the cap by a fixed amount whatever N; UGDK's bias is
    # O(1/N), invisible under the seed-to-seed scatter at N = 1e4 .. 1e5.
    t = _bias_table(half_angle, sigma)
    g_small, _ = t["gdke", 1_000]
    g_big, g_big_se = t["gdke", 100_000]
    u_big, u_big_se = t["ugdk", 100_000]
    u_mid, u_mid_se = t["ugdk", 10_000]
    assert g_big > 20 * g_big_se  # GDKE's bias is real...
    assert 0.6 < g_big / g_small < 1.5  # ...and does not shrink with N
    assert u_big < 4 * u_big_se  # UGDK: no bias detectable at N = 1e5
    assert u_mid < 4 * u_mid_se
    assert g_big > 20 * u_big
    # the noise estimate is consistent
    assert abs(t["sigma", 100_000] / sigma - 1) < 0.02


def test_full_sphere_both_unbiased():
    # by symmetry GDKE has no bias on the full sphere: both agree
    t = _bias_table(180.0, 0.05, sizes=(10_000,), seeds=12)
    for k in ("gdke", "ugdk"):
        bias, se = t[k, 10_000]
        assert bias < 4 * se


def test_ugdk_with_known_sigma_matches_estimated():
    rng = np.random.default_rng(5)
    sigma = 0.03
    X = _cap(rng, 50_000, 45.0) + rng.normal(0, sigma, (50_000, 3))
    a, b = ugdk(X, sigma), ugdk(X)
    assert a.ok and b.ok
    assert a.sigma == sigma
    assert abs(b.sigma / sigma - 1) < 0.02
    assert np.linalg.norm(a.centre - b.centre) < 0.01


def test_ugdk_close_to_cramer_rao_bound():
    # RMS centre error over seeds against sqrt(trace(CRLB)) for the same directions
    sigma, n = 0.05, 10_000
    err, bound = [], []
    for seed in range(10):
        rng = np.random.default_rng([seed, 11])
        U = _cap(rng, n, 90.0)
        X = U + rng.normal(0, sigma, (n, 3))
        err.append(np.linalg.norm(ugdk(X).centre))
        bound.append(np.sqrt(np.trace(sphere_crlb(U, sigma))))
    ratio = np.sqrt(np.mean(np.square(err))) / np.mean(bound)
    assert 0.6 < ratio < 1.6


def test_mle_beats_lls_on_small_cap():
    sigma, n = 0.02, 300
    e_mle, e_lls = [], []
    for seed in range(10):
        rng = np.random.default_rng([seed, 3])
        X = _cap(rng, n, 30.0) + rng.normal(0, sigma, (n, 3))
        m = sphere_mle(X)
        assert m.ok, m.reason
        assert m.iterations > 0
        e_mle.append(np.linalg.norm(m.centre))
        e_lls.append(np.linalg.norm(sphere_lls(X).centre))
    assert np.mean(e_mle) < 0.5 * np.mean(e_lls)


def test_lls_is_the_gdke_estimator():
    rng = np.random.default_rng(4)
    X = CENTRE + 300 * _cap(rng, 2000, 50.0) + rng.normal(0, 3.0, (2000, 3))
    a, b, c = gdke(X), sphere_lls(X), sphere_lls(X, solver="lstsq")
    np.testing.assert_allclose(b.centre, a.centre, atol=1e-8)
    np.testing.assert_allclose(c.centre, a.centre, atol=1e-8)
    np.testing.assert_allclose(b.radii, a.radii, atol=1e-8)


# ---------------------------------------------------------------- multi-radius


def test_mgdk_noisy_with_gaps_beats_its_worst_marker():
    rng = np.random.default_rng(6)
    radii = np.array([40.0, 150.0, 300.0])
    n = 3000
    U = np.stack([_cap(rng, n, 70.0, axis=np.array([1.0, 1.0, 0.0])) for _ in radii], axis=1)
    X = CENTRE + radii[None, :, None] * U + rng.normal(0, 2.0, (n, 3, 3))
    X[rng.random((n, 3)) < 0.3] = np.nan  # per-marker gaps
    fit = mgdk(X)
    assert fit.ok, fit.reason
    singles = [ugdk(X[:, k]) for k in range(3)]
    err = np.linalg.norm(fit.centre - CENTRE)
    assert err < max(np.linalg.norm(s.centre - CENTRE) for s in singles)
    assert err < 1.0
    np.testing.assert_allclose(fit.radii, radii, atol=1.0)
    assert abs(fit.sigma / 2.0 - 1) < 0.1
    # the same data as a sequence of per-marker arrays, NaN rows dropped
    seq = [x[np.isfinite(x).all(1)] for x in X.transpose(1, 0, 2)]
    np.testing.assert_allclose(mgdk(seq).centre, fit.centre, atol=1e-9)


# ---------------------------------------------------------------- IGDK


def test_igdk_equals_batch_in_any_split():
    rng = np.random.default_rng(7)
    n = 5000
    X = CENTRE + 200 * _cap(rng, n, 60.0) + rng.normal(0, 1.5, (n, 3))
    X[rng.random(n) < 0.1, rng.integers(0, 3)] = np.nan
    cuts = np.sort(rng.choice(np.arange(1, n), size=12, replace=False))
    inc = IGDK()
    inc.update(np.full((4, 3), np.nan))  # an all-NaN batch
    for part in np.split(X, cuts):
        inc.update(part)
    inc.update(np.empty((0, 3)))  # an empty batch
    for sigma, batch in ((0.0, gdke(X)), (None, ugdk(X)), (1.5, ugdk(X, 1.5))):
        got = inc.result(sigma)
        assert got.ok and got.method == "igdk"
        assert got.n == batch.n
        np.testing.assert_allclose(got.centre, batch.centre, rtol=0, atol=1e-9)
        np.testing.assert_allclose(got.radii, batch.radii, rtol=1e-12)
        assert got.sigma == pytest.approx(batch.sigma, rel=1e-9, abs=1e-12)
        assert got.rms == pytest.approx(batch.rms, rel=1e-6)


def test_igdk_multi_marker_equals_mgdk():
    rng = np.random.default_rng(8)
    radii = np.array([60.0, 180.0])
    n = 3000
    U = np.stack([_cap(rng, n, 80.0) for _ in radii], axis=1)
    X = CENTRE + radii[None, :, None] * U + rng.normal(0, 1.0, (n, 2, 3))
    X[rng.random((n, 2)) < 0.2] = np.nan
    inc = IGDK(n_markers=2)
    for part in np.array_split(X, 7):
        inc.update(part)
    for sigma in (0.0, None):
        np.testing.assert_allclose(inc.result(sigma).centre, mgdk(X, sigma).centre, rtol=0, atol=1e-9)
        np.testing.assert_allclose(inc.result(sigma).radii, mgdk(X, sigma).radii, rtol=1e-12)
    with pytest.raises(ValueError):
        inc.update(X[:, :1])  # the number of markers cannot change


def test_igdk_without_samples_is_a_failed_fit():
    fit = IGDK().result()
    assert not fit and not fit.ok and fit.reason
    assert np.isnan(fit.centre).all()


# ---------------------------------------------------------------- NaN and failures


@pytest.mark.parametrize("name", list(_methods_single()))
def test_nan_rows_are_ignored(name):
    rng = np.random.default_rng(9)
    X = CENTRE + 150 * _cap(rng, 600, 70.0) + rng.normal(0, 1.0, (600, 3))
    Xn = X.copy()
    holes = rng.random(600) < 0.2
    Xn[holes, rng.integers(0, 3)] = np.nan
    method = _methods_single()[name]
    a, b = method(Xn), method(X[~holes])
    assert a.ok and b.ok
    assert a.n == b.n == int((~holes).sum())
    np.testing.assert_allclose(a.centre, b.centre, rtol=0, atol=1e-6 if name == "mle" else 1e-9)


@pytest.mark.parametrize("method", [gdke, ugdk, mgdk, sphere_lls, sphere_mle])
def test_too_few_samples_is_a_failed_fit(method):
    X = np.array([[1.0, 0, 0], [0, 1, 0], [0, 0, 1], [np.nan, 0, 0]])
    fit = method(X)
    assert not fit.ok and "too few" in fit.reason
    assert np.isnan(fit.centre).all() and np.isnan(fit.radii).all()


@pytest.mark.parametrize("method", [gdke, ugdk, mgdk, sphere_lls])
def test_coplanar_samples_are_a_failed_fit(method):
    # a marker on a circle (hinge): the centre is free along the circle's axis
    t = np.linspace(0, 2, 200)
    X = CENTRE + 100 * np.column_stack([np.cos(t), np.sin(t), np.zeros_like(t)])
    fit = method(X)
    assert not fit.ok and "coplanar" in fit.reason


def test_sigma_beyond_the_spread_fails_leontief():
    rng = np.random.default_rng(10)
    X = _cap(rng, 1000, 10.0)  # depth spread ~ 0.004
    fit = ugdk(X, sigma=0.1)
    assert not fit.ok and "Leontief" in fit.reason


def test_bad_shapes_raise():
    with pytest.raises(ValueError):
        gdke(np.zeros((10, 2)))
    with pytest.raises(ValueError):
        mgdk(np.zeros((10, 2, 2)))
    with pytest.raises(ValueError):
        ugdk(np.zeros((10, 3)), sigma=-1.0)


# ---------------------------------------------------------------- CRLB


def test_crlb_full_sphere_closed_form():
    # uniform full sphere: sum (u - mean u)(u - mean u)^T ~ N/3 I, so trace ~ 9 sigma^2 / N
    rng = np.random.default_rng(12)
    n, sigma = 100_000, 0.1
    cov = sphere_crlb(_cap(rng, n, 180.0), sigma)
    assert np.trace(cov) == pytest.approx(9 * sigma**2 / n, rel=0.02)
    np.testing.assert_allclose(cov, cov.T)


def test_crlb_grows_as_the_cap_shrinks_and_is_infinite_on_a_circle():
    rng = np.random.default_rng(13)
    tr = [np.trace(sphere_crlb(_cap(rng, 5000, a), 1.0)) for a in (90.0, 45.0, 20.0)]
    assert tr[0] < tr[1] < tr[2]
    t = np.linspace(0, 6, 100)
    circle = np.column_stack([np.cos(t), np.sin(t), np.full_like(t, 0.5)])
    assert np.isinf(sphere_crlb(circle, 1.0)).all()


def test_moments_of_several_markers_at_once_equal_marker_by_marker():
    """The batched central sums (every marker seen equally often) equal the per-marker ones."""
    from mocapskel.solvers.spheres import moments as sphere_moments

    rng = np.random.default_rng(31)
    X = rng.normal(0, 50, (3000, 4, 3)) + [1000.0, -500, 2000]
    batch = sphere_moments._moments([X[:, p] for p in range(4)])
    for p in range(4):
        n, mean, M2, T, Q = sphere_moments._marker_sums(X[:, p])
        assert batch.n[p] == n
        np.testing.assert_allclose(batch.mean[p], mean, rtol=1e-15)
        np.testing.assert_allclose(batch.M2[p], M2, rtol=1e-12)
        np.testing.assert_allclose(batch.T[p], T, rtol=1e-9, atol=1e-9 * np.abs(T).max())
        assert batch.Q[p] == pytest.approx(Q, rel=1e-12)
    # unequal sample counts (gaps) take the per-marker path: the same sums
    Xg = X.copy()
    Xg[::7, 1] = np.nan
    gaps = sphere_moments._moments([Xg[:, p] for p in range(4)])
    assert gaps.n[1] < gaps.n[0]
    np.testing.assert_allclose(gaps.M2[[0, 2, 3]], batch.M2[[0, 2, 3]], rtol=1e-12)


def test_brentq_gives_scipys_root_to_the_last_bit():
    """The port of Brent's method finds SciPy's root exactly (SciPy's own ``brentq`` is the reference),
    on smooth functions of several kinds and tolerances, including the ones the noise estimate uses."""
    from scipy.optimize import brentq as scipy_brentq

    from mocapskel.solvers.spheres.solve import brentq

    rng = np.random.default_rng(7)
    checked = 0
    for i in range(3000):
        c = rng.normal(size=6)
        f = [lambda x: np.polyval(c, x), lambda x: np.sin(3 * c[0] * x) + c[1] * x - c[2],
             lambda x: np.tanh(5 * (x - c[0])) + 1e-3 * c[1]][i % 3]
        a, b = sorted(rng.uniform(-3, 3, 2))
        if not np.sign(f(a)) * np.sign(f(b)) < 0:
            continue
        xtol, rtol = [(1e-12, 4 * np.finfo(float).eps), (1e-15 * abs(b), 1e-15), (1e-6, 1e-10)][i % 3]
        assert brentq(f, a, b, xtol=xtol, rtol=rtol, maxiter=200) == scipy_brentq(f, a, b, xtol=xtol, rtol=rtol, maxiter=200)
        checked += 1
    assert checked > 1000


def test_brentq_refuses_what_scipy_refuses():
    from mocapskel.solvers.spheres.solve import brentq

    with pytest.raises(ValueError, match="different signs"):
        brentq(lambda x: x * x + 1.0, -1.0, 1.0, xtol=1e-12, rtol=1e-15, maxiter=100)
    with pytest.raises(ValueError, match="NaN"):
        brentq(lambda x: np.nan if x > 0.1 else x - 0.5, 0.0, 1.0, xtol=1e-12, rtol=1e-15, maxiter=100)
    with pytest.raises(RuntimeError, match="no convergence"):
        brentq(lambda x: np.exp(x) - 1.5, 0.0, 1.0, xtol=1e-300, rtol=4 * np.finfo(float).eps, maxiter=2)
    assert brentq(lambda x: x, 0.0, 1.0, xtol=1e-12, rtol=1e-15, maxiter=5) == 0.0


def test_a_fit_does_not_import_scipy_optimize(tmp_path):
    """Importing ``scipy.optimize`` or ``scipy.spatial`` costs a third of a second or more; a fit of a
    take whose joints use the sphere fit (a one-marker segment: its noise estimate is Brent's root) and
    whose refinement looks for joints outside the body's hull does without them."""
    import subprocess
    import sys
    from dataclasses import replace

    from mocapskel.io.markers import write_markers
    from mocapskel.synth.presets import make, realistic

    take = make(realistic(seed=1, frames=240, motion="walk", markerset="cmu41"))  # (the generator uses SciPy)
    write_markers(tmp_path / "take.c3d", replace(take.markers, source="take.c3d"))
    code = (
        "import sys, mocapskel\n"
        "from mocapskel import pipeline\n"
        "from mocapskel.solvers.spheres import solve as sphere_solve\n"
        "calls = []\n"
        "plain = sphere_solve.brentq\n"
        "sphere_solve.brentq = lambda *a, **k: calls.append(1) or plain(*a, **k)\n"
        "res = pipeline.fit('take.c3d', pipeline.make_params(up='z', units='mm'))\n"
        "print(len(calls), res.report['refinement'].get('iterations', 0) > 0,"
        " 'scipy.optimize' in sys.modules, 'scipy.spatial' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=tmp_path).stdout.split()
    assert int(out[0]) > 0  # the root was needed
    assert out[1] == "True"  # the refinement ran (it looks for joints outside the hull)
    assert out[2:] == ["False", "False"]
