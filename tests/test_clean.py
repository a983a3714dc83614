import numpy as np
from dataclasses import replace

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
