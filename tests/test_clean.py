import numpy as np
import pytest
from dataclasses import replace

from mocapskel.errors import DataError
from mocapskel.stages import clean


def test_planted_jumps_become_gaps(linkage):
    m = linkage.markers
    pts = m.points.copy()
    rng = np.random.default_rng(0)
    planted = np.zeros(pts.shape[:2], dtype=bool)
    for _ in range(30):
        f, k = int(rng.integers(50, pts.shape[0] - 50)), int(rng.integers(pts.shape[1]))
        d = int(rng.integers(2, 6))
        pts[f : f + d, k] += rng.normal(size=3) / np.sqrt(3) * 100.0 + 60.0
        planted[f : f + d, k] = True
    out = clean.run(replace(m, points=pts))
    found = ~np.isfinite(out.points).all(-1)
    assert found[planted].mean() > 0.97
    # besides the jumps only their edges are trimmed (trim_frames on each side)
    from scipy.ndimage import binary_dilation

    k = clean.Params().trim_frames
    near = binary_dilation(planted, structure=np.ones((2 * k + 1, 1), dtype=bool))
    assert (found & ~near).mean() < 0.001
    assert out.info["clean"]["jump_samples"] >= planted.sum() * 0.97


def test_gap_edges_trimmed_and_short_runs_dropped(linkage):
    m = linkage.markers
    pts = m.points.copy()
    pts[1000:1100, 0] = np.nan  # a gap
    pts[:, 1] = np.nan
    pts[500:530, 1] = m.points[500:530, 1]  # a 0.25 s run: dropped
    pts[:, 2] = np.nan
    pts[600:700, 2] = m.points[600:700, 2]  # a 0.83 s run: kept, trimmed at both ends
    p = clean.Params(trim_frames=3)
    out = clean.run(replace(m, points=pts), p)
    vis = np.isfinite(out.points).all(-1)
    # marker 1 has nothing left: removed
    assert m.labels[1] not in out.labels
    i0, i2 = out.labels.index(m.labels[0]), out.labels.index(m.labels[2])
    assert not vis[997:1103, i0].any() and vis[996, i0] and vis[1103, i0]
    assert not vis[:603, i2].any() and vis[603:697, i2].all() and not vis[697:, i2].any()
    # the take's own ends are not gap edges
    assert vis[0, i0] and vis[-1, i0]
    assert out.info["clean"]["dropped_markers"] == [m.labels[1]]


# --------------------------------------------------------------------------- the vectorised kernels against plain references


def _reference_find_jumps(points: np.ndarray, rate: float, params: clean.Params) -> np.ndarray:
    """find_jumps written plainly: full hold-fill, np.linalg.norm, np.median windows, scipy dilation."""
    import warnings

    from scipy import ndimage

    F, M, _ = points.shape
    vis = np.isfinite(points).all(axis=2)
    if F < 5:
        return np.zeros((F, M), dtype=bool)
    w = max(5, int(round(params.jump_window_s * rate)) | 1)
    h = w // 2
    filled = np.nan_to_num(clean.hold_fill(points, vis), nan=0.0)
    step = np.full((F, M), np.inf)
    with np.errstate(invalid="ignore"):
        step[1:] = np.linalg.norm(points[1:] - points[:-1], axis=2)
    big = ~(step <= 0.5 * params.jump_mm)
    big[0] = False
    cand = ndimage.binary_dilation(big, structure=np.ones((2 * h + 3, 1), dtype=bool)) & vis
    sampled = np.zeros((F, M), dtype=bool)
    sampled[:: max(1, F // 2000)] = True
    sampled &= vis
    fi, mi = np.nonzero(cand | sampled)
    dev = np.full((F, M), np.nan)
    win = filled[np.clip(fi[:, None] + np.arange(-h, h + 1), 0, F - 1), mi[:, None]]
    dev[fi, mi] = np.linalg.norm(points[fi, mi] - np.median(win, axis=1), axis=1)
    mad = np.zeros(M)
    has = sampled.any(axis=0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        mad[has] = np.nanmedian(np.where(sampled, dev, np.nan)[:, has], axis=0)
    thresh = np.maximum(params.jump_mm, params.jump_mad * 1.4826 * np.nan_to_num(mad))
    with np.errstate(invalid="ignore"):
        off = cand & (dev > thresh[None, :])
    for f, m in zip(*np.nonzero(off)):  # kept where the path is seen whole over the window and smooth
        if f - h >= 0 and f + h < F and vis[f - h : f + h + 1, m].all():
            p = points[f - h : f + h + 1, m]
            third = p[3:] - 3.0 * p[2:-1] + 3.0 * p[1:-2] - p[:-3]
            off[f, m] = np.linalg.norm(third, axis=1).max() >= 0.5 * params.jump_mm
    return off


def _reference_run(markers, params: clean.Params):
    """clean.run written plainly (scipy.ndimage for erosion and run labels); returns (points, info)."""
    from scipy import ndimage

    pts = markers.points.copy()
    F = pts.shape[0]
    vis0 = np.isfinite(pts).all(axis=2)
    pts[~vis0] = np.nan
    candidates = _reference_find_jumps(pts, markers.rate, params)
    # the candidates of markers with rigid partners are judged by them (tested on their own below)
    jumps = clean.rigid_verdict(pts, vis0, candidates, markers.rate, params) if params.rigid else candidates
    vis = vis0 & ~jumps
    trimmed = np.zeros_like(vis)
    if params.trim_frames > 0 and F > 2 * params.trim_frames:
        k = params.trim_frames
        kept = ndimage.binary_erosion(vis, structure=np.ones((2 * k + 1, 1), dtype=bool), border_value=1)
        trimmed, vis = vis & ~kept, kept
    lab, n = ndimage.label(vis, structure=np.array([[0, 1, 0]] * 3, dtype=bool))
    short = np.bincount(lab.ravel(), minlength=n + 1) < max(1, int(np.ceil(params.min_run_s * markers.rate)))
    short[0] = False
    short_mask = short[lab]
    vis &= ~short_mask
    pts[~vis] = np.nan
    keep = vis.any(axis=0)
    info = {"jump_samples": int(jumps.sum()), "jump_candidates": int(candidates.sum()), "trimmed_samples": int((trimmed & ~jumps).sum()),
            "short_run_samples": int((short_mask & ~trimmed).sum()), "short_runs": int(short[1:].sum()),
            "visible_before": int(vis0.sum()), "visible_after": int(vis.sum())}
    return pts[:, keep], info


def _messy_take():
    from mocapskel.synth.presets import Recipe, make

    m = make(Recipe(kind="human", seed=3, frames=2500, noise_mm=1.0, gaps_per_marker_per_minute=30, jumps=40, ghosts=6)).markers
    pts = m.points.copy()
    pts[::9, 3] = np.nan  # flicker: many short runs
    pts[100:104, 5] += 400.0  # a planted jump
    pts[:, 7] = np.nan  # never seen
    pts[10, 8, 1] = np.inf  # an infinite coordinate
    pts[20, 9, 0] = np.nan  # one NaN coordinate
    return replace(m, points=pts)


@pytest.mark.parametrize(
    "params",
    [clean.Params(), clean.Params(trim_frames=0), clean.Params(trim_frames=3, min_run_s=0.1), clean.Params(jump_mm=5.0, jump_mad=3.0)],
)
def test_run_equals_the_plain_reference(params):
    m = _messy_take()
    for mk in (m, replace(m, points=m.points[:40].copy()), replace(m, points=m.points[:4].copy())):
        ref_pts, ref_info = _reference_run(mk, params)
        if ref_pts.shape[1] == 0:  # nothing left: refused
            with pytest.raises(DataError, match="no marker has a visible run"):
                clean.run(mk, params)
            continue
        out = clean.run(mk, params)
        np.testing.assert_array_equal(out.points, ref_pts)
        assert {k: out.info["clean"][k] for k in ref_info} == ref_info
        assert np.array_equal(clean.find_jumps(mk.points, mk.rate, params), _reference_find_jumps(mk.points, mk.rate, params))


def test_hold_fill_holds_the_last_seen_value():
    rng = np.random.default_rng(4)
    pts = rng.normal(size=(50, 6, 3))
    vis = rng.random((50, 6)) < 0.6
    vis[:, 2] = False  # never seen
    vis[:7, 3] = False  # leading gap
    pts[~vis] = np.nan
    out = clean.hold_fill(pts, vis)
    for m in range(6):
        seen = np.flatnonzero(vis[:, m])
        for f in range(50):
            if not seen.size:
                assert np.isnan(out[f, m]).all()
            else:
                src = seen[seen <= f][-1] if (seen <= f).any() else seen[0]
                np.testing.assert_array_equal(out[f, m], pts[src, m])


def test_no_warning_for_infinite_coordinates():
    import warnings

    m = _messy_take()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        clean.run(m)


def test_consume_reuses_the_input_array_and_changes_nothing_else():
    from mocapskel.synth.presets import Recipe, make

    m = make(Recipe(kind="human", seed=4, frames=1500, noise_mm=1.0, gaps_per_marker_per_minute=20, jumps=20,
                    ghosts=8)).markers
    plain = clean.run(m)
    mine = replace(m, points=m.points.copy())
    owned = clean.run(mine, consume=True)
    assert np.shares_memory(owned.points, mine.points)  # no second copy of the take
    assert not np.shares_memory(plain.points, m.points)
    assert owned.labels == plain.labels and owned.info["clean"] == plain.info["clean"]
    assert len(plain.labels) < m.n_markers  # some markers were dropped: the in-place compaction was exercised
    np.testing.assert_array_equal(owned.points, plain.points)


# --------------------------------------------------------------------------- fast motion is not a jump


FAST_CHAIN = (4, 3, 3, 4, 3, 3, 3, 3)  # Hang's <4-3-3-4-3-3-3-3>: 26 markers


def _fast_chain(links: int, seed: int, frames: int = 600):
    from mocapskel.synth.chains import hang_chain

    return hang_chain(FAST_CHAIN[:links], frames, rng=np.random.default_rng(seed), link_length=1000.0)


@pytest.mark.parametrize("links", [4, 6, 8])
def test_noise_free_fast_chain_keeps_every_marker_and_segment(links):
    """A noise-free chain of links of 1 m at 100 Hz lost 12 of its 26 markers to clean (286 samples called
    jumps because the far links move fast) and 4 of its 8 segments from the BVH."""
    from mocapskel import pipeline

    take = _fast_chain(links, seed=0)
    assert take.markers.rate == 100.0
    speed = np.linalg.norm(np.diff(take.markers.points, axis=0), axis=-1).max() * take.markers.rate
    assert speed > 5000.0  # markers faster than 5 m/s: the old test called such samples jumps
    out = clean.run(take.markers)
    info = out.info["clean"]
    assert info["jump_samples"] == 0 and info["dropped_markers"] == [] and info["jump_candidates"] > 0
    assert out.n_markers == take.markers.n_markers
    res = pipeline.fit(take.markers, pipeline.make_params())
    assert len(res.motion.skeleton.names) == links


@pytest.mark.parametrize("seed", [0, 1])
def test_planted_jumps_in_a_fast_chain_become_gaps(seed):
    """The rigid test still finds the generator's jumps where the markers move fast."""
    from mocapskel.synth import corrupt

    take = corrupt.add_jumps(_fast_chain(4, seed, 1000), np.random.default_rng(seed + 10), n_jumps=20)
    planted = corrupt.bad_sample_mask(take)
    out = clean.run(take.markers)
    assert out.n_markers == take.markers.n_markers
    found = ~np.isfinite(out.points).all(-1)
    assert found[planted].mean() >= 0.97
    from scipy.ndimage import binary_dilation

    near = binary_dilation(planted, structure=np.ones((2 * clean.Params().trim_frames + 1, 1), dtype=bool))
    assert (found & ~near).mean() < 0.01


def test_rigid_verdict_without_partners_keeps_the_candidates():
    """A marker seen with fewer than two rigid partners is judged by its path alone."""
    rng = np.random.default_rng(0)
    F = 600
    pts = np.cumsum(rng.normal(size=(F, 2, 3)), axis=0) * 5.0  # two unrelated markers
    pts = np.concatenate([pts, pts[:, :1] + 100.0], axis=1)  # one partner for marker 0 (not two)
    vis = np.ones((F, 3), dtype=bool)
    cand = np.zeros((F, 3), dtype=bool)
    cand[100:103, 0] = True
    np.testing.assert_array_equal(clean.rigid_verdict(pts, vis, cand, 100.0), cand)


def test_neighbour_median_is_the_sorted_median_bit_for_bit():
    """The jump test's median of the four neighbouring changes (a sorting network) gives what
    ``np.sort`` gives (NaN last): the mean of the middle two of four seen, the middle one of three,
    the mean of two, NaN with fewer; and the vector norms are ``np.linalg.norm``'s, bit for bit."""
    from mocapskel.solvers.merging.jumps import _neighbour_median, norm3

    rng = np.random.default_rng(5)
    for dtype in (np.float32, np.float64):
        dr = rng.normal(size=(300, 40, 3)).astype(dtype) * 10
        dr[rng.random((300, 40)) < 0.3] = np.nan  # unseen changes, in runs and alone
        dr[0] = np.nan
        dr[50:60, :5] = np.nan
        dr[rng.random((300, 40)) < 0.05] = 3.0  # ties
        F = dr.shape[0]
        nbs = np.full((4,) + dr.shape, np.nan, dtype=dtype)
        for q, k in enumerate((-2, -1, 1, 2)):
            if k < 0:
                nbs[q, -k:] = dr[:k]
            else:
                nbs[q, :-k] = dr[k:]
        nbs.sort(axis=0)
        cnt = np.isfinite(nbs[:, ..., 0]).sum(0)[..., None]
        want = np.where(cnt == 4, 0.5 * (nbs[1] + nbs[2]),
                        np.where(cnt == 3, nbs[1], np.where(cnt == 2, 0.5 * (nbs[0] + nbs[1]), np.nan)))
        got = _neighbour_median(dr)
        assert got.dtype == dtype and got.shape == (F, 40, 3)
        np.testing.assert_array_equal(got, want)  # NaN where NaN, every other value equal
        assert np.array_equal(norm3(dr), np.linalg.norm(dr, axis=-1), equal_nan=True)


def _swing(seed: int, jump: tuple[int, int] | None = None) -> tuple[np.ndarray, float]:
    """One marker (10 s at 120 Hz, 0.5 mm noise) drifting round a circle of 0.5 m that swings once, at 5 s, at up to
    10 m/s (85 mm a frame, accelerations up to 16 mm a frame squared: a hand in a fast swing); ``jump`` = (first
    frame, frames) plants a 45 mm jump."""
    rng = np.random.default_rng(seed)
    rate, F = 120.0, 1200
    t = np.arange(F) / rate
    th = np.cumsum(0.3 + 20.0 * np.exp(-0.5 * ((t - 5.0) / 0.12) ** 2)) / rate
    p = np.stack([500.0 * np.cos(th), 500.0 * np.sin(th), 1000.0 + 20.0 * np.sin(t)], axis=1) + rng.normal(0, 0.5, (F, 3))
    if jump is not None:
        p[jump[0] : jump[0] + jump[1], 2] += 45.0
    return p[:, None, :], rate


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_fast_swing_on_a_smooth_path_is_no_jump_and_a_jump_in_it_is(seed):
    """The plain median of a window lies 30 mm and more off a path that curves this fast (it flagged 6-7 samples of
    the swing; a real take lost 18 frames of both hands' markers so); a path seen whole and smooth over the window
    (third differences under half the jump size) has no jump in it. A marker with no partners is judged by its path
    alone, so these are its verdicts: no sample of the swing is a jump; 45 mm jumps of two frames in the swing and
    of three frames before it are found, with at most a frame beside them."""
    P, rate = _swing(seed)
    assert not clean.find_jumps(P, rate).any()
    for first, n in [(600, 2), (200, 3)]:
        P, rate = _swing(seed, (first, n))
        found = set(np.flatnonzero(clean.find_jumps(P, rate)[:, 0]).tolist())
        assert set(range(first, first + n)) <= found <= set(range(first - 1, first + n + 1))


def test_grown_runs_are_scipys_binary_propagation_along_time():
    """The jumps' growth through their soft neighbours (runs of the mask along time that hold a seed, those over
    ``max_len`` frames left out) against scipy's binary propagation with a time-only structure, on random masks."""
    from scipy import ndimage

    from mocapskel.solvers.merging.jumps import grow_runs, runs_of

    rng = np.random.default_rng(5)
    vert = np.zeros((3, 3), dtype=bool)
    vert[:, 1] = True
    for _ in range(200):
        F, L = int(rng.integers(1, 90)), int(rng.integers(1, 7))
        mask = rng.random((F, L)) < rng.random()
        seed = mask & (rng.random((F, L)) < 0.15)
        max_len = int(rng.integers(1, 25))
        ref = ndimage.binary_propagation(seed, structure=vert, mask=mask)
        np.testing.assert_array_equal(grow_runs(seed, mask), ref)
        col, a, b = runs_of(ref)
        for c, x, y in zip(col, a, b):
            if y - x > max_len:
                ref[x:y, c] = False
        np.testing.assert_array_equal(grow_runs(seed, mask, max_len), ref)
