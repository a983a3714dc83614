"""Clean: remove what optical systems get wrong (Kirk et al. 2005, §3).

- sporadic jumps: samples that leave the marker's own smooth path for a few
  frames are candidates (off the median of a short window, unless the path
  is seen whole and smooth over it: a fast curve is no jump); a candidate of
  a marker seen with two or more rigid partners (markers whose distance to
  it hardly varies over the take) is a jump only when it leaves those
  partners (by distance or by the abrupt change of the vectors to them,
  :func:`~mocapskel.solvers.merging.jumps.rigid_jumps`),
  so that fast motion keeps its samples; a marker without two partners in
  view is judged by its path alone. Jumps are turned into gaps;
- gap edges: a few frames at both ends of every visible run that borders a
  gap are trimmed (reconstruction is poor there);
- short runs: visible runs shorter than ``min_run_s`` (ghosts, flicker) are
  dropped; a marker left with nothing is removed.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, replace

import numpy as np

from ..artifacts import Markers
from ..errors import DataError
from ..model.measures import visible
from ..solvers.merging.jumps import judged_by_partners, norm3, rigid_jumps
from ..solvers.merging.pairs import _auto_rigid, pair_sums, partners_of
from ..solvers.parallel import run_blocks

VERSION = 5


@dataclass(frozen=True)
class Params:
    trim_frames: int = 2
    """Frames removed at each gap-side end of a visible run."""
    min_run_s: float = 0.5
    """Visible runs shorter than this (seconds) are dropped."""
    jump_mm: float = 30.0
    """A sample farther than this from its marker's running median is a jump..."""
    jump_mad: float = 10.0
    """...and also farther than this many robust deviations (MAD) of that marker."""
    jump_window_s: float = 0.08
    """Width of the running median used to find jump candidates (at least 5 frames)."""
    rigid: bool = True
    """Judge the candidates of markers seen with two or more rigid partners against those
    partners (False: every candidate is a jump, whatever the partners say)."""
    rigid_jump_mm: float = 20.0
    """A sample farther than this (or 6 std) from its usual distance to most of its partners has left them."""
    rigid_step_mm: float = 40.0
    """...or one whose vectors to most partners change this much more than they turn from frame to frame."""
    max_jump_s: float = 0.3
    """Longer departures from the partners are not sporadic jumps."""
    partner_s: float = 2.0
    """Partners that judge jumps must be seen together this long, or for half the take if it is shorter
    than twice that: in a take of 1 s no pair could qualify, and every candidate was a jump (a noise-free
    chain of 8 links of 300 mm whipping at up to 38 m/s lost its last two links for 0.4 s)."""


#: Samples (frames x markers) per block where clean works through a take in blocks of frames.
_BLOCK_SAMPLES = 1 << 20
#: Samples whose running-median windows are gathered at once (per thread: two threads hold what one
#: chunk of 200,000 did).
_WINDOW_CHUNK = 100_000


def _window_any(mask: np.ndarray, before: int, after: int) -> np.ndarray:
    """Per column, whether any of ``mask[f - before : f + after + 1]`` is True (outside the array: False).

    A running count, a block of columns at a time (its temporaries stay small on long takes).
    """
    F, M = mask.shape
    out = np.empty((F, M), dtype=bool)
    step = max(1, _BLOCK_SAMPLES // max(F, 1))
    for lo in range(0, M, step):
        sub = mask[:, lo : lo + step]
        # running count, padded so that every window is one difference of two slices
        c = np.zeros((before + F + after + 1, sub.shape[1]), dtype=np.int32)
        np.cumsum(sub, axis=0, dtype=np.int32, out=c[before + 1 : before + F + 1])
        c[before + F + 1 :] = c[before + F]
        np.greater(c[before + after + 1 :], c[:F], out=out[:, lo : lo + step])
    return out


def _short_runs(vis: np.ndarray, min_run: int) -> tuple[np.ndarray, int]:
    """Visible runs (along time, per marker) shorter than ``min_run`` frames.

    Returns (mask (F, M) of their samples, number of such runs).
    """
    F, M = vis.shape
    edge = np.zeros((M, F + 2), dtype=np.int8)  # marker-major: runs are contiguous
    edge[:, 1:-1] = vis.T
    d = np.diff(edge, axis=1)  # +1 where a run starts, -1 one past its end
    ms, fs = np.nonzero(d == 1)  # both in (marker, frame) order, so the k-th start and end are one run
    me, fe = np.nonzero(d == -1)
    short = fe - fs < min_run
    delta = np.zeros((M, F + 1), dtype=np.int8)
    delta[ms[short], fs[short]] = 1
    delta[me[short], fe[short]] = -1  # an end never coincides with a start (runs are separated by gaps)
    return np.cumsum(delta[:, :F], axis=1, dtype=np.int8).T.astype(bool), int(short.sum())


def _hold_index(vis: np.ndarray) -> np.ndarray:
    """(F, M) frame index :func:`hold_fill` takes each sample from (F - 1 for markers never seen)."""
    F = vis.shape[0]
    idx = np.where(vis, np.arange(F, dtype=np.int32)[:, None], np.int32(-1))
    np.maximum.accumulate(idx, axis=0, out=idx)
    # before its first sighting a marker holds its first seen value
    first = np.where(vis.any(axis=0), np.argmax(vis, axis=0), F - 1).astype(np.int32)
    np.copyto(idx, first[None, :], where=idx < 0)
    return idx


def hold_fill(points: np.ndarray, visible: np.ndarray) -> np.ndarray:
    """Fill gaps by holding the last seen value (leading gaps: the first seen value).

    points : (F, M, 3) ndarray; visible : (F, M) bool. Markers never seen stay NaN.
    """
    idx = _hold_index(visible)
    return np.take_along_axis(points, idx[:, :, None], axis=0)


def find_jumps(points: np.ndarray, rate: float, params: Params = Params()) -> np.ndarray:
    """Flag sporadic jumps.

    Parameters
    ----------
    points : (F, M, 3) ndarray, NaN for gaps.
    rate : frames per second.

    Returns
    -------
    (F, M) bool ndarray, True where a sample is a jump.
    """
    return _find_jumps(points, visible(points), rate, params)


def _find_jumps(points: np.ndarray, vis: np.ndarray, rate: float, params: Params) -> np.ndarray:
    F, M, _ = points.shape
    if F < 5:
        return np.zeros((F, M), dtype=bool)
    w = max(5, int(round(params.jump_window_s * rate)) | 1)
    h = w // 2
    # The running median is only needed where a jump can be: next to a step larger
    # than half the jump size (or a gap edge), plus a sparse sampling of frames
    # for each marker's robust spread (MAD). Its windows read the gap-filled
    # track (hold_fill) through the hold index, at the window frames only.
    step = np.empty((F, M))
    step[0] = np.inf
    blk = max(1, _BLOCK_SAMPLES // max(M, 1))  # frames at a time: the differences of a whole long take are large

    def steps(lo: int) -> None:  # blocks write their own frames: side by side on the cores
        hi = min(F, lo + blk)
        with np.errstate(invalid="ignore"):  # inf - inf in a gap
            d = np.subtract(points[lo:hi], points[lo - 1 : hi - 1])
        d *= d
        np.add(d[..., 0], d[..., 1], out=step[lo:hi])  # np.linalg.norm's order: (x² + y²) + z²
        step[lo:hi] += d[..., 2]

    run_blocks(steps, range(1, F, blk))
    np.sqrt(step, out=step)
    big = ~(step <= 0.5 * params.jump_mm)  # NaN (gap edge) counts as big
    big[0] = False
    del step
    cand = _window_any(big, h + 1, h + 1)
    del big
    cand &= vis
    every = max(1, F // 2000)
    sampled = np.zeros((F, M), dtype=bool)
    sampled[::every] = vis[::every]
    fi, mi = np.nonzero(cand | sampled)
    hold = _hold_index(vis).ravel()
    flat = points.reshape(F * M, 3)
    dev = np.empty(fi.size)  # the deviation of each of those samples (only they are needed)
    offs = np.arange(-h, h + 1)

    def deviations(k: int) -> None:  # chunks bound the memory of the windows; each writes its own samples
        f, m = fi[k : k + _WINDOW_CHUNK], mi[k : k + _WINDOW_CHUNK]
        src = np.take(hold, np.clip(f[:, None] + offs, 0, F - 1) * M + m[:, None])  # (K, w) frames
        win = np.take(flat, src * M + m[:, None], axis=0)  # (K, w, 3), every sample seen
        med = np.partition(win, h, axis=1)[:, h]  # the median of an odd window
        dev[k : k + _WINDOW_CHUNK] = norm3(flat[f * M + m] - med)

    run_blocks(deviations, range(0, fi.size, _WINDOW_CHUNK))
    del hold
    # the MAD over the sampled frames only (rows never sampled hold nothing)
    is_s = sampled[fi, mi]
    d_s = np.full((sampled[::every].shape[0], M), np.nan)
    d_s[fi[is_s] // every, mi[is_s]] = dev[is_s]
    has = sampled[::every].any(axis=0)
    mad = np.zeros(M)
    if has.any():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            mad[has] = np.nanmedian(d_s[:, has], axis=0)
    mad = np.nan_to_num(mad, nan=0.0)
    thresh = np.maximum(params.jump_mm, params.jump_mad * 1.4826 * mad)
    jumps = np.zeros((F, M), dtype=bool)
    is_c = cand[fi, mi]
    off = is_c & (dev > thresh[mi])
    fo, mo = fi[off], mi[off]
    jumps[fo, mo] = ~_smooth_around(points, vis, fo, mo, h, 0.5 * params.jump_mm)
    return jumps


def _smooth_around(points: np.ndarray, vis: np.ndarray, f: np.ndarray, m: np.ndarray, h: int,
                   bar: float) -> np.ndarray:
    """For samples (f, m) off their window's median: whether the marker's path is seen whole over the window
    (frames f - h ... f + h) and smooth there, its third differences all under ``bar``.

    A jump of J moves the third differences next to it by J or more (a one-frame jump: J, -3J, 3J, -J; the
    edges of a longer one: J, -2J, J), while a path that only curves fast keeps them at its jerk and noise: a
    hand sweeping an arc at 10 m/s lies 30 mm and more off the plain median of ten frames, and a real take
    lost 18 frames of both hands' markers so, where their third differences stayed at 4.2 mm or less.
    """
    F = points.shape[0]
    out = np.zeros(f.size, dtype=bool)
    frames = f[:, None] + np.arange(-h, h + 1)
    inside = ((frames >= 0) & (frames < F)).all(axis=1)
    idx = np.flatnonzero(inside)
    fr, mk = frames[idx], m[idx, None]
    seen = vis[fr, mk].all(axis=1)
    idx, fr, mk = idx[seen], fr[seen], mk[seen]
    if idx.size:
        third = np.diff(points[fr, mk], n=3, axis=1)  # (K, w - 3, 3)
        out[idx] = norm3(third).max(axis=1) < bar
    return out


#: (frame, pair) distances sampled to find rigid partners (a fifth of what merge-ids uses: partners
#: need only be found, not told apart from relabelled markers; 0.3 s less on a 1-minute take).
_PAIR_ENTRIES = 600_000
#: Frames per block of the rigid test (with ``_margin`` frames of context on both sides).
_RIGID_BLOCK = 4096


def rigid_verdict(points: np.ndarray, vis: np.ndarray, candidates: np.ndarray, rate: float,
                  params: Params = Params()) -> np.ndarray:
    """Which jump candidates are jumps: judged against rigid partners where a marker has them.

    Parameters
    ----------
    points : (F, M, 3) ndarray, non-finite where unseen.
    vis : (F, M) bool ndarray, the samples seen.
    candidates : (F, M) bool ndarray, samples off the marker's smooth path (:func:`find_jumps`).
    rate : frames per second.

    Returns
    -------
    (F, M) bool ndarray
        At samples seen with two or more reliable rigid partners: the rigid
        test's verdict (:func:`~mocapskel.solvers.merging.jumps.rigid_jumps`), and the
        candidates that also leave most of those partners by half its distance
        (its *soft* samples), in the blocks of frames around candidates;
        elsewhere the candidates.
    """
    F, M = vis.shape
    if not candidates.any() or M < 3 or F < 5:
        return candidates.copy()
    rate = float(rate) if rate and rate > 0 else 1.0
    pts = points
    if not np.array_equal(vis, visible(points)):  # some sample's visibility is not its points' finiteness
        pts = np.where(vis[..., None], points, np.nan)
    sums = pair_sums(pts, vis, max_entries=_PAIR_ENTRIES)
    min_shared = max(3, int(np.ceil(0.15 * rate / sums.stride)))
    mean, std = sums.stats()
    rigid_mm = _auto_rigid(std, sums.n, min_shared)
    # partners: rigid within the take's own tolerance over 2 s or more, with at most 5 % of their
    # shared frames trimmed (a marker's own jumps take a few per cent of them)
    together = min(params.partner_s * rate, 0.5 * F)
    reliable = partners_of(mean, std, sums.n, rigid_mm, max(min_shared, int(together / sums.stride)),
                           sums.shared, 0.05)
    judged = judged_by_partners(vis, reliable)
    out = candidates & ~judged
    todo = (candidates & judged).any(axis=1)
    if not todo.any():
        return out
    max_len = max(1, int(round(params.max_jump_s * rate)))
    margin = 2 * max_len + 8

    def block(a: int) -> None:
        # blocks are independent (each reads its frames with their margins and writes its own frames
        # only), so they run on the cores side by side
        b = min(F, a + _RIGID_BLOCK)
        lo, hi = max(0, a - margin), min(F, b + margin)
        jumps, soft = rigid_jumps(pts[lo:hi], vis[lo:hi], mean, std, reliable, jump_mm=params.rigid_jump_mm,
                                  step_mm=params.rigid_step_mm, max_len=max_len)
        # a jump: what the rigid test finds, and a candidate off its path that also leaves most of
        # its partners by half the rigid test's distance (a small jump the partners see less well)
        jumps |= soft & candidates[lo:hi]
        out[a:b] |= jumps[a - lo : b - lo] & judged[a:b]

    run_blocks(block, [a for a in range(0, F, _RIGID_BLOCK) if todo[a : a + _RIGID_BLOCK].any()])
    return out


def run(markers: Markers, params: Params = Params(), *, consume: bool = False) -> Markers:
    """Clean a take: jumps to gaps, trim gap edges, drop short runs and empty markers.

    Returns a new Markers with ``stage="clean"`` and ``info["clean"]`` counting
    what was removed and why. Raises DataError when nothing is left.
    ``consume=True``: the caller will not use ``markers`` again, and its points
    array becomes the output's (compacted in place) instead of being copied —
    what keeps a long passive take (hundreds of labels) within memory.
    """
    F, M, _ = markers.points.shape
    vis0 = visible(markers.points)
    # the jump test reads visible samples only and takes any non-finite step as large,
    # so the points need not have their gaps set to NaN before it
    jumps = _find_jumps(markers.points, vis0, markers.rate, params)
    n_candidates = int(np.count_nonzero(jumps))
    if params.rigid:
        jumps = rigid_verdict(markers.points, vis0, jumps, markers.rate, params)
    vis = vis0 & ~jumps

    trimmed = np.zeros_like(vis)
    if params.trim_frames > 0 and F > 2 * params.trim_frames:
        k = params.trim_frames
        # a binary erosion along time with the take's ends counted as visible
        kept = vis & ~_window_any(~vis, k, k)
        trimmed = vis & ~kept
        # never trim a run away entirely: keep runs that would vanish (they are judged by length next)
        vis = kept

    min_run = max(1, int(np.ceil(params.min_run_s * markers.rate)))
    short_mask, n_short = _short_runs(vis, min_run)
    vis &= ~short_mask

    keep = vis.any(axis=0)
    dropped = [markers.labels[i] for i in np.flatnonzero(~keep)]
    if not keep.any():
        raise DataError(
            "no marker has a visible run of at least "
            f"{params.min_run_s:g} s after cleaning — the take is too short or too broken to fit",
            markers.source or None,
        )
    cols = np.flatnonzero(keep)
    src = markers.points
    if consume and src.dtype == np.float64 and src.flags.writeable:
        for j, c in enumerate(cols):  # the kept markers moved left, in place (c >= j)
            if c != j:
                src[:, j] = src[:, c]
        pts = src[:, : cols.size]
    else:
        pts = src.copy() if cols.size == M else src[:, cols]
    # gaps, jumps, trimmed edges and short runs: NaN (in place, no index arrays)
    np.copyto(pts, np.nan, where=~(vis if cols.size == M else vis[:, cols])[..., None])
    info = dict(markers.info)
    info["clean"] = {
        "version": VERSION,
        "jump_samples": int(np.count_nonzero(jumps)),
        "jump_candidates": n_candidates,
        "trimmed_samples": int(np.count_nonzero(trimmed & ~jumps)),
        "short_run_samples": int(np.count_nonzero(short_mask & ~trimmed)),
        "short_runs": n_short,
        "dropped_markers": dropped,
        "visible_before": int(np.count_nonzero(vis0)),
        "visible_after": int(np.count_nonzero(vis)),
    }
    return replace(
        markers,
        points=pts,
        labels=tuple(l for l, k in zip(markers.labels, keep) if k),
        stage="clean",
        info=info,
    )
