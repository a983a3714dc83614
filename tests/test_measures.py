"""The subject's extent and the visibility kernel against their plain computations."""
from __future__ import annotations

import numpy as np

from mocapskel.model.measures import marker_extent, visible


def _take(seed: int = 0, F: int = 1000, M: int = 9) -> np.ndarray:
    rng = np.random.default_rng(seed)
    pts = rng.normal(0.0, 300.0, (F, M, 3))
    pts[rng.random((F, M)) < 0.2] = np.nan
    pts[rng.random((F, M)) < 0.02, 1] = np.inf  # one coordinate alone not finite
    return pts


def test_visible_is_all_coordinates_finite() -> None:
    pts = _take()
    np.testing.assert_array_equal(visible(pts), np.isfinite(pts).all(-1))


def test_extent_of_some_markers_by_index_or_by_mask() -> None:
    """``columns`` reads the same frames of those markers alone: as indices or as a mask, the extent of the
    take cut down to them (a mask taken as indices 0 and 1 measured the first two markers only)."""
    pts = _take(1)
    mask = np.zeros(pts.shape[1], dtype=bool)
    mask[[1, 4, 5, 8]] = True
    ref = marker_extent(pts[:, mask])
    assert np.isfinite(ref) and ref > 0
    assert marker_extent(pts, columns=mask) == ref
    assert marker_extent(pts, columns=np.flatnonzero(mask)) == ref
    assert marker_extent(pts, columns=np.array([8, 1, 5, 4])) == ref  # the order of the markers does not matter
