"""Corruptions of a synthetic take: noise, gaps, jumps, ghosts, relabelling, losses.

Every function takes a :class:`~mocapskel.synth.truth.SynthTake` and returns a
new one (the input is never modified) whose truth stays consistent with its
labels. What was done is appended to ``truth.info["corruptions"]``, and the
samples that were put out of place are recorded per *physical* marker (so the
records survive relabelling) as ``[marker_id, start, stop]`` frame runs
(``stop`` exclusive):

- ``truth.info["gaps"]``        occlusion gaps planted by :func:`add_gaps`;
- ``truth.info["bad_samples"]`` displaced samples at gap edges;
- ``truth.info["jumps"]``       ``[marker_id, start, stop, dx, dy, dz]``;
- ``truth.info["lost"]``        ``[start, stop]`` ranges where nothing is seen.

:func:`bad_sample_mask` turns the records into an ``(F, M)`` mask over the
take's current labels. A realistic order is ``add_gaps`` → ``add_jumps`` →
``add_ghosts`` → ``relabel_passive`` (noise anywhere); ``drop_markers``
first or last.
"""
from __future__ import annotations

import copy
import re
from collections.abc import Mapping

import numpy as np

from .truth import SynthTake

__all__ = [
    "add_noise",
    "add_gaps",
    "add_jumps",
    "add_ghosts",
    "relabel_passive",
    "drop_markers",
    "everything_lost",
    "bad_sample_mask",
    "visible_runs",
]


# --------------------------------------------------------------------------- helpers


def visible_runs(visible: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Start and stop (exclusive) frames of the runs of True in a (F,) bool array."""
    v = np.concatenate([[False], np.asarray(visible, bool), [False]])
    d = np.diff(v.astype(np.int8))
    return np.flatnonzero(d == 1), np.flatnonzero(d == -1)


def _rebuild(
    take: SynthTake,
    op: dict,
    *,
    points: np.ndarray | None = None,
    labels: tuple[str, ...] | None = None,
    marker_segment: np.ndarray | None = None,
    marker_id: np.ndarray | None = None,
    info: dict | None = None,
) -> SynthTake:
    """A new take with some fields replaced and ``op`` appended to the corruption log."""
    info = copy.deepcopy(take.truth.info) if info is None else info
    info.setdefault("corruptions", []).append(op)
    m, tr = take.markers, take.truth
    markers = type(m)(
        points=m.points.copy() if points is None else points,
        labels=m.labels if labels is None else labels,
        rate=m.rate,
        units=m.units,
        source=m.source,
        stage=m.stage,
        info=copy.deepcopy(m.info),
    )
    truth = type(tr)(
        segment_names=tr.segment_names,
        parent=tr.parent.copy(),
        marker_segment=tr.marker_segment.copy() if marker_segment is None else marker_segment,
        marker_id=tr.marker_id.copy() if marker_id is None else marker_id,
        joint_child=tr.joint_child.copy(),
        joints=tr.joints.copy(),
        bone_length=tr.bone_length.copy(),
        info=info,
    )
    return SynthTake(markers=markers, truth=truth)


def _physical_ids(take: SynthTake) -> np.ndarray:
    ids = take.truth.marker_id
    return np.unique(ids[ids >= 0])


def _random_directions(rng: np.random.Generator, n: int) -> np.ndarray:
    v = rng.standard_normal((n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


# --------------------------------------------------------------------------- corruptions


def add_noise(take: SynthTake, sigma_mm: float, rng: np.random.Generator) -> SynthTake:
    """White Gaussian noise of standard deviation ``sigma_mm`` on every coordinate seen.

    Parameters
    ----------
    take : SynthTake
    sigma_mm : float
        Standard deviation per coordinate (mm).
    rng : numpy.random.Generator

    Returns
    -------
    SynthTake
        ``points`` (F, M, 3) with noise added (NaN stays NaN); truth unchanged.
    """
    if sigma_mm < 0:
        raise ValueError(f"sigma_mm must be non-negative, got {sigma_mm}")
    pts = take.markers.points + rng.normal(0.0, float(sigma_mm), take.markers.points.shape)
    return _rebuild(take, {"op": "add_noise", "sigma_mm": float(sigma_mm)}, points=pts)


def add_gaps(
    take: SynthTake,
    rng: np.random.Generator,
    gaps_per_marker_per_minute: float = 4.0,
    mean_gap_s: float = 0.3,
    bad_edge_frames: int = 2,
    bad_edge_mm: float = 30.0,
) -> SynthTake:
    """Occlusion gaps (NaN runs) with displaced samples at their edges.

    For every physical marker (ghosts are left alone) a Poisson number of gaps
    with mean ``gaps_per_marker_per_minute`` per minute start at uniformly
    random frames and last an exponential time of mean ``mean_gap_s`` (at
    least one frame); overlapping gaps merge. The ``bad_edge_frames`` visible
    frames before and after every gap are displaced, each in a random
    direction by ``bad_edge_mm`` times U(0.5, 1.5), as when a blob is partly
    hidden.

    Parameters
    ----------
    take : SynthTake
    rng : numpy.random.Generator
    gaps_per_marker_per_minute : float
    mean_gap_s : float
    bad_edge_frames : int
        Frames corrupted on each side of a gap (0: none).
    bad_edge_mm : float
        Typical displacement of a bad edge sample.

    Returns
    -------
    SynthTake
        With NaN gaps; ``truth.info["gaps"]`` and ``["bad_samples"]`` hold
        the ``[marker_id, start, stop]`` runs.
    """
    pts = take.markers.points.copy()
    F = pts.shape[0]
    rate = take.markers.rate
    lam = gaps_per_marker_per_minute * F / rate / 60.0
    mid = take.truth.marker_id
    info = copy.deepcopy(take.truth.info)
    gaps_rec, bad_rec = info.setdefault("gaps", []), info.setdefault("bad_samples", [])
    n_gaps = n_bad = 0
    for p in _physical_ids(take):
        cols = np.flatnonzero(mid == p)
        vis = ~np.isnan(pts[:, cols, 0])  # (F, C)
        n = rng.poisson(lam)
        starts = rng.integers(0, F, n)
        lengths = np.maximum(1, np.round(rng.exponential(mean_gap_s, n) * rate).astype(int))
        gap = np.zeros(F + 1, dtype=int)
        np.add.at(gap, starts, 1)
        np.add.at(gap, np.minimum(starts + lengths, F), -1)
        gap = np.cumsum(gap[:F]) > 0
        if not gap.any():
            continue
        dil = gap.copy()
        for k in range(1, int(bad_edge_frames) + 1):
            dil[k:] |= gap[:-k]
            dil[:-k] |= gap[k:]
        edge = dil & ~gap & vis.any(1)
        fe = np.flatnonzero(edge)
        disp = _random_directions(rng, fe.size) * (bad_edge_mm * rng.uniform(0.5, 1.5, fe.size))[:, None]
        for j, c in enumerate(cols):
            on = vis[fe, j]
            pts[fe[on], c] += disp[on]
        pts[np.ix_(gap, cols)] = np.nan
        for s, e in zip(*visible_runs(gap)):
            gaps_rec.append([int(p), int(s), int(e)])
            n_gaps += 1
        for s, e in zip(*visible_runs(edge)):
            bad_rec.append([int(p), int(s), int(e)])
        n_bad += fe.size
    op = {
        "op": "add_gaps",
        "gaps_per_marker_per_minute": float(gaps_per_marker_per_minute),
        "mean_gap_s": float(mean_gap_s),
        "bad_edge_frames": int(bad_edge_frames),
        "bad_edge_mm": float(bad_edge_mm),
        "n_gaps": n_gaps,
        "n_bad_samples": int(n_bad),
    }
    return _rebuild(take, op, points=pts, info=info)


def add_jumps(
    take: SynthTake,
    rng: np.random.Generator,
    n_jumps: int = 10,
    jump_mm: tuple[float, float] = (50.0, 150.0),
    duration_frames: tuple[int, int] = (2, 10),
) -> SynthTake:
    """Sporadic jumps: a marker leaves its rigid place for a few frames.

    Each jump picks a physical marker and a frame where it is seen, and moves
    its samples over the next U{duration_frames} frames by one random vector
    of length U(jump_mm).

    Parameters
    ----------
    take : SynthTake
    rng : numpy.random.Generator
    n_jumps : int
    jump_mm : (2,) floats
        Range of the jump length (mm).
    duration_frames : (2,) ints
        Inclusive range of the jump duration (frames).

    Returns
    -------
    SynthTake
        ``truth.info["jumps"]`` holds ``[marker_id, start, stop, dx, dy, dz]``.
    """
    pts = take.markers.points.copy()
    F = pts.shape[0]
    mid = take.truth.marker_id
    phys = _physical_ids(take)
    info = copy.deepcopy(take.truth.info)
    rec = info.setdefault("jumps", [])
    done = 0
    for _ in range(int(n_jumps)):
        if phys.size == 0:
            break
        p = int(rng.choice(phys))
        cols = np.flatnonzero(mid == p)
        seen = np.flatnonzero(~np.isnan(pts[:, cols, 0]).all(1))
        d = int(rng.integers(duration_frames[0], duration_frames[1] + 1))
        vec = _random_directions(rng, 1)[0] * rng.uniform(*jump_mm)
        if seen.size == 0:
            continue
        s = int(rng.choice(seen))
        e = min(F, s + d)
        pts[s:e, cols] += vec  # NaN stays NaN
        rec.append([p, s, e, *(float(x) for x in vec)])
        done += 1
    op = {"op": "add_jumps", "n_jumps": done, "jump_mm": list(map(float, jump_mm)),
          "duration_frames": list(map(int, duration_frames))}  # fmt: skip
    return _rebuild(take, op, points=pts, info=info)


def _is_anonymous(labels: tuple[str, ...]) -> bool:
    return bool(labels) and all(re.fullmatch(r"M\d+", lab) for lab in labels)


def add_ghosts(
    take: SynthTake,
    rng: np.random.Generator,
    n_ghosts: int = 25,
    duration_s: tuple[float, float] = (0.05, 0.4),
    radius_mm: float = 1200.0,
) -> SynthTake:
    """Short-lived extra labels not attached to anything (reflections, merged blobs).

    Each ghost lives U(duration_s) seconds from a random frame, starts at a
    random point within ``radius_mm`` (horizontally) of the subject's centre
    (the mean true joint centre) at 0–2000 mm height, and half of them drift
    at 0.1–1.5 m/s.

    Parameters
    ----------
    take : SynthTake
    rng : numpy.random.Generator
    n_ghosts : int
    duration_s : (2,) floats
    radius_mm : float

    Returns
    -------
    SynthTake
        With ``n_ghosts`` labels appended, ``marker_segment`` and
        ``marker_id`` -1. They are named ``M<n>`` after the existing labels
        when those are anonymous (relabelled), else ``GHOST<n>``.
    """
    m = take.markers
    F, M = m.points.shape[:2]
    n = int(n_ghosts)
    g = np.full((F, n, 3), np.nan)
    J = take.truth.joints
    centre = J.mean(axis=1) if J.shape[1] else np.zeros((F, 3))  # (F, 3)
    for k in range(n):
        dur = max(1, int(round(rng.uniform(*duration_s) * m.rate)))
        dur = min(dur, F)
        s = int(rng.integers(0, F - dur + 1))
        ang, rad = rng.uniform(0.0, 2.0 * np.pi), radius_mm * np.sqrt(rng.uniform())
        p0 = np.array([centre[s, 0] + rad * np.cos(ang), centre[s, 1] + rad * np.sin(ang), rng.uniform(0.0, 2000.0)])
        drifting = rng.uniform() < 0.5
        vel = _random_directions(rng, 1)[0] * rng.uniform(100.0, 1500.0) if drifting else np.zeros(3)
        g[s : s + dur, k] = p0 + np.outer(np.arange(dur) / m.rate, vel)
    taken = set(m.labels)
    names: list[str] = []
    if _is_anonymous(m.labels):
        nxt = max(int(lab[1:]) for lab in m.labels) + 1
        width = max(4, len(str(nxt + n)))
        fmt = lambda i: f"M{i:0{width}d}"  # noqa: E731
    else:
        nxt = 1
        fmt = lambda i: f"GHOST{i:02d}"  # noqa: E731
    while len(names) < n:
        lab = fmt(nxt)
        nxt += 1
        if lab not in taken:
            names.append(lab)
    op = {"op": "add_ghosts", "n_ghosts": n, "duration_s": list(map(float, duration_s)), "radius_mm": float(radius_mm)}
    info = copy.deepcopy(take.truth.info)
    if "relabel_source" in info:  # ghosts added after relabelling come from no earlier label
        info["relabel_source"] = list(info["relabel_source"]) + [-1] * n
    return _rebuild(
        take,
        op,
        info=info,
        points=np.concatenate([m.points, g], axis=1),
        labels=m.labels + tuple(names),
        marker_segment=np.concatenate([take.truth.marker_segment, np.full(n, -1)]),
        marker_id=np.concatenate([take.truth.marker_id, np.full(n, -1)]),
    )


def relabel_passive(take: SynthTake, rng: np.random.Generator, p_new_label: float = 1.0) -> SynthTake:
    """Passive-system labelling: a marker gets a new label whenever it reappears.

    Every visible run of every label (ghosts included) becomes a label of its
    own (with probability ``p_new_label`` per reappearance; otherwise the run
    keeps the label of the one before). Labels are ``M0001``, ``M0002`` … in
    order of first appearance, ties broken at random. Labels never seen are
    dropped. Two labels of one physical marker are never seen in one frame.

    Parameters
    ----------
    take : SynthTake
    rng : numpy.random.Generator
    p_new_label : float
        Probability that a reappearing marker gets a new label (1: always).

    Returns
    -------
    SynthTake
        ``truth.marker_id`` / ``marker_segment`` map every new label to its
        physical marker / segment; ``truth.info["relabel_source"]`` gives the
        index of the label it came from (-1 for ghosts added afterwards). Memory grows with the number of
        labels: (F, L, 3), mostly NaN.
    """
    pts = take.markers.points
    F, M = pts.shape[:2]
    vis = ~np.isnan(pts[..., 0])
    spans: list[tuple[int, int, int]] = []  # (first frame, stop, source label)
    for lab in range(M):
        starts, stops = visible_runs(vis[:, lab])
        if starts.size == 0:
            continue
        new = np.concatenate([[True], rng.uniform(size=starts.size - 1) < p_new_label])
        first = np.flatnonzero(new)
        last = np.concatenate([first[1:], [starts.size]]) - 1
        spans.extend((int(starts[a]), int(stops[b]), lab) for a, b in zip(first, last))
    L = len(spans)
    tie = rng.permutation(L)
    order = sorted(range(L), key=lambda i: (spans[i][0], tie[i]))
    out = np.full((F, L, 3), np.nan)
    src = np.empty(L, dtype=int)
    for j, i in enumerate(order):
        s, e, lab = spans[i]
        out[s:e, j] = pts[s:e, lab]
        src[j] = lab
    width = max(4, len(str(L)))
    labels = tuple(f"M{j + 1:0{width}d}" for j in range(L))
    info = copy.deepcopy(take.truth.info)
    info["relabel_source"] = src.tolist()
    op = {"op": "relabel_passive", "p_new_label": float(p_new_label), "n_labels_before": M, "n_labels": L}
    return _rebuild(
        take,
        op,
        points=out,
        labels=labels,
        marker_segment=take.truth.marker_segment[src].copy(),
        marker_id=take.truth.marker_id[src].copy(),
        info=info,
    )


def drop_markers(take: SynthTake, keep_per_segment: int | Mapping[str, int], rng: np.random.Generator) -> SynthTake:
    """Keep at most ``keep_per_segment`` physical markers on every segment.

    The kept markers are a random subset; every label of a dropped marker is
    removed (ghosts stay). Physical markers are renumbered 0..P-1 in their
    old order, and the per-marker truth records follow.

    Parameters
    ----------
    take : SynthTake
    keep_per_segment : int or {segment name: int}
        Markers to keep per segment (segments not in a mapping keep all).
    rng : numpy.random.Generator

    Returns
    -------
    SynthTake
        ``truth.info["kept_markers"]`` lists the old ids of the kept markers.
    """
    tr = take.truth
    keep_ids: list[int] = []
    for s, name in enumerate(tr.segment_names):
        k = keep_per_segment.get(name) if isinstance(keep_per_segment, Mapping) else int(keep_per_segment)
        ids = np.unique(tr.marker_id[(tr.marker_segment == s) & (tr.marker_id >= 0)])
        if k is not None and ids.size > k:
            ids = np.sort(rng.choice(ids, size=int(k), replace=False))
        keep_ids.extend(int(i) for i in ids)
    kept = np.array(sorted(keep_ids), dtype=int)
    n_old = int(tr.marker_id.max()) + 1 if tr.marker_id.size and tr.marker_id.max() >= 0 else 0
    new_id = np.full(max(n_old, 1), -1)
    new_id[kept] = np.arange(kept.size)
    cols = np.flatnonzero((tr.marker_id < 0) | np.isin(tr.marker_id, kept))
    mid = np.where(tr.marker_id[cols] >= 0, new_id[np.maximum(tr.marker_id[cols], 0)], -1)
    info = copy.deepcopy(tr.info)
    for key in ("gaps", "bad_samples", "jumps"):
        if key in info:
            info[key] = [[int(new_id[r[0]])] + list(r[1:]) for r in info[key] if new_id[r[0]] >= 0]
    for key in ("rest_markers_mm", "physical_labels"):
        if key in info and len(info[key]) == n_old:
            info[key] = [info[key][i] for i in kept]
    if len(info.get("relabel_source", ())) == tr.marker_id.size:
        info["relabel_source"] = [info["relabel_source"][c] for c in cols]
    info["kept_markers"] = [int(kept_old) for kept_old in kept]
    if isinstance(keep_per_segment, Mapping):
        spec: int | dict = {str(k): int(v) for k, v in keep_per_segment.items()}
    else:
        spec = int(keep_per_segment)
    op = {"op": "drop_markers", "keep_per_segment": spec, "n_markers": int(kept.size)}
    return _rebuild(
        take,
        op,
        points=take.markers.points[:, cols].copy(),
        labels=tuple(take.markers.labels[c] for c in cols),
        marker_segment=tr.marker_segment[cols].copy(),
        marker_id=mid,
        info=info,
    )


def everything_lost(take: SynthTake, frame_range: tuple[int, int]) -> SynthTake:
    """Every marker unseen over frames ``[start, stop)`` (truth joints kept).

    Parameters
    ----------
    take : SynthTake
    frame_range : (start, stop) ints
        Python slice bounds; clipped to the take.

    Returns
    -------
    SynthTake
        ``truth.info["lost"]`` gets ``[start, stop]``.
    """
    F = take.markers.n_frames
    s, e = (max(0, min(F, int(x))) for x in frame_range)
    pts = take.markers.points.copy()
    pts[s:e] = np.nan
    info = copy.deepcopy(take.truth.info)
    info.setdefault("lost", []).append([s, e])
    return _rebuild(take, {"op": "everything_lost", "frame_range": [s, e]}, points=pts, info=info)


def bad_sample_mask(take: SynthTake) -> np.ndarray:
    """Samples put out of their rigid place by gap edges or jumps.

    Parameters
    ----------
    take : SynthTake

    Returns
    -------
    mask : (F, M) bool ndarray
        True for a *visible* sample of a label whose physical marker has a
        ``bad_samples`` or ``jumps`` record at that frame (noise and soft
        tissue do not count).
    """
    pts = take.markers.points
    F, M = pts.shape[:2]
    mask = np.zeros((F, M), dtype=bool)
    mid = take.truth.marker_id
    for rec in take.truth.info.get("bad_samples", []) + take.truth.info.get("jumps", []):
        p, s, e = int(rec[0]), int(rec[1]), int(rec[2])
        mask[s:e, mid == p] = True
    return mask & ~np.isnan(pts[..., 0])
