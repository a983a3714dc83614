"""Merge-ids: labels that are one physical marker become one (Kirk et al. 2005, §4).

Passive systems give a marker a new label after every gap and add ghost
points; a take often has 2–4 times more labels than markers. Everything here
rests on rigidity: a label's *partners* are the labels whose distance to it
stays constant (std ≤ ``rigid_mm``) over the frames they share.

1. Ghosts: labels seen for a short time (under ``ghost_max_s``) and rigidly
   attached to nothing are dropped.
2. Linking (beyond the paper; fast and sure): a label that ends and one that
   starts soon after (within ``max_gap_s``) where the ending label's partners
   put it — the same mean distance to at least two partners of both — are
   joined by an assignment (Hungarian) pass, only when the best match beats
   every rival by ``margin_mm``. Repeated until nothing changes, since every
   join makes longer tracks and more common partners. When two or three
   markers of one body were lost together (a single common partner, or none:
   whole triangles matched by their side lengths), the candidate links are
   tried together and each is kept only if it then has two common partners.
3. Kirk's clustering for what is left: the distance between two tracks never
   seen together is the common-partner distance when they share two
   partners, else Kirk's pose distance (smallest distance after rigid
   alignment of the markers the two frames share, sampled then refined;
   kept only when clearly the best). Tracks seen together repel (Yu & Shi):
   spectral clustering with attraction and repulsion, per connected group of
   candidates, into as many clusters as the group has tracks seen at once
   (Kirk's count of physical markers, per group); every merge is checked.
   Linking and clustering alternate until neither joins anything.
4. Late ghosts: short tracks that never move (a still reflection is rigid to
   every still marker) and that no physical marker could be are dropped.
5. Outliers, on the merged markers (whose partners are now well tested):
   sporadic jumps (a marker leaving its partners for at most ``max_jump_s``,
   found by distance and by the abrupt change of the vectors to them) become
   gaps, and doubtful samples next to a gap are trimmed.

Never are two labels seen in the same frame merged (every join is checked
against the exact frames each label is seen). The number of physical markers
is the most markers seen in one frame after ghost removal (Kirk).

Output: one label per physical marker, named after its longest source label;
``info["merge_ids"]["merged"]`` maps every output label to its source labels,
``info["merge_ids"]["dropped"]`` says what was removed and why. When every
marker is lost at once, labels before and after cannot be matched (Kirk's
failure case): the take is merged in pieces and a warning says so.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np

from ..artifacts import Markers
from ..errors import DataError
from ..model.measures import visible
from ..solvers.merging.cluster import pose_distance, repulsion_spectral, time_gaps
from ..solvers.merging.jumps import rigid_jumps, runs_of
from ..solvers.merging.links import common_partner_cost, link_tracks, triangle_links
from ..solvers.merging.pairs import _auto_rigid, pair_sums, partners_of, track_sums

log = logging.getLogger("mocapskel")

VERSION = 2


@dataclass(frozen=True)
class Params:
    enabled: bool = True
    """False: labels pass through unchanged (only the count is recorded)."""
    rigid_mm: float | None = None
    """Largest distance std (mm) of rigid partners; None: twice the typical std of
    a label's most rigid partner, within [2, 15] mm."""
    min_shared_s: float = 0.15
    """Two labels must be seen together this long to be judged rigid."""
    ghost_max_s: float = 2.0
    """Labels seen for less than this (and less than a quarter of the take), rigid
    to nothing or that no physical marker could be, are ghosts."""
    max_gap_s: float = 2.0
    """Linking: longest gap between a label's end and the next one's start."""
    link_mm: float = 4.0
    """Largest rms difference of mean partner distances for one marker."""
    margin_mm: float = 4.0
    """A link must beat every rival by this much."""
    pose_mm: float = 12.0
    """Largest Kirk pose distance for one marker."""
    max_speed_mm_s: float = 5000.0
    """Fastest plausible marker speed across a gap."""
    jump_mm: float = 20.0
    """A sample farther than this (or 6 std) from its usual distance to most of
    its partners is a jump; half of it, next to a gap, a bad edge."""
    step_mm: float = 40.0
    """A label whose vectors to most of its partners change this much more (and 8
    times more) than they turn from frame to frame has jumped (any direction)."""
    edge_frames: int = 3
    """Frames next to a gap checked for bad edge samples."""
    reliable_s: float = 2.0
    """Partners that judge jumps must be seen together this long."""
    max_jump_s: float = 0.3
    """Longer departures from the partners are not sporadic jumps (left alone)."""
    max_trimmed: float = 0.05
    """Pairs whose distance departs from its usual value in more than this share of
    the frames they share are not rigid partners (a joint that moved for a while)."""
    max_rounds: int = 30
    """Most linking rounds (each usually joins many labels at once)."""
    seed: int = 0


@dataclass
class _State:
    """Track-level view of the labels for one grouping (track: (L,) int, -1 for dropped)."""

    track: np.ndarray
    n_tracks: int
    first: np.ndarray
    last: np.ndarray
    p_first: np.ndarray
    p_last: np.ndarray
    mean: np.ndarray
    std: np.ndarray
    n: np.ndarray
    shared: np.ndarray
    partner: np.ndarray
    overlap: np.ndarray
    vis: np.ndarray | None = None
    points: np.ndarray | None = None


class _Merger:
    def __init__(self, markers: Markers, params: Params):
        self.p = params
        pts = np.asarray(markers.points, dtype=float)
        fin = [np.isfinite(pts[..., c]) for c in range(3)]  # per coordinate: no (F, L, 3) temporaries
        vis = fin[0] & fin[1] & fin[2]
        if ((fin[0] | fin[1] | fin[2]) & ~vis).any():  # a partly missing sample is missing
            pts = pts.copy()
            np.copyto(pts, np.nan, where=~vis[..., None])
        del fin
        self.points, self.vis = pts, vis
        self.rate = float(markers.rate) if markers.rate and markers.rate > 0 else 1.0
        self.F, self.L = vis.shape
        self.sums = pair_sums(pts, vis)
        self.min_shared = max(3, int(np.ceil(params.min_shared_s * self.rate / self.sums.stride)))
        mean, std = self.sums.stats()
        self.rigid_mm = float(params.rigid_mm) if params.rigid_mm is not None else _auto_rigid(std, self.sums.n, self.min_shared)
        self.label_partner = partners_of(mean, std, self.sums.n, self.rigid_mm, self.min_shared,
                                         self.sums.shared, params.max_trimmed)
        self.label_overlap = _run_overlap(vis)
        self.pose_cache: dict[tuple, float] = {}
        seen = vis.any(axis=0)
        self.first = np.where(seen, vis.argmax(axis=0), self.F)
        self.last = np.where(seen, self.F - 1 - vis[::-1].argmax(axis=0), -1)
        ar = np.arange(self.L)
        self.p_first = pts[np.minimum(self.first, self.F - 1), ar]
        self.p_last = pts[np.maximum(self.last, 0), ar]

    # ---------------------------------------------------------------- track views

    def state(self, track: np.ndarray, *, full: bool = True) -> _State:
        T = int(track.max()) + 1 if track.size and track.max() >= 0 else 0
        ts = track_sums(self.sums, track, T)
        mean, std = ts.stats()
        partner = partners_of(mean, std, ts.n, self.rigid_mm, self.min_shared, ts.shared, self.p.max_trimmed)
        ok = np.flatnonzero(track >= 0)
        t = track[ok]
        key = (t[:, None] * T + t[None, :]).ravel()
        overlap = np.rint(
            np.bincount(key, weights=self.label_overlap[np.ix_(ok, ok)].ravel(), minlength=T * T)
        ).astype(np.int64).reshape(T, T)
        # first and last frames of every track, and its positions there
        first = np.full(T, self.F)
        last = np.full(T, -1)
        p_first = np.full((T, 3), np.nan)
        p_last = np.full((T, 3), np.nan)
        if ok.size:
            o = ok[np.lexsort((self.first[ok], t))]
            head = np.r_[True, track[o][1:] != track[o][:-1]]
            first[track[o][head]] = self.first[o][head]
            p_first[track[o][head]] = self.p_first[o][head]
            o = ok[np.lexsort((-self.last[ok], t))]
            head = np.r_[True, track[o][1:] != track[o][:-1]]
            last[track[o][head]] = self.last[o][head]
            p_last[track[o][head]] = self.p_last[o][head]
        st = _State(track, T, first, last, p_first, p_last, mean, std, ts.n, ts.shared, partner, overlap)
        if full:
            st.vis = np.zeros((self.F, T), dtype=bool)
            st.points = np.full((self.F, T, 3), np.nan)
            r, c = np.nonzero(self.vis & (track >= 0)[None, :])
            st.vis[r, track[c]] = True
            st.points[r, track[c]] = self.points[r, c]
        return st


def _run_overlap(vis: np.ndarray) -> np.ndarray:
    """(L, L) exact number of frames two labels are both seen, from their visible runs."""
    F, L = vis.shape
    col, start, stop = runs_of(vis)
    out = np.zeros(L * L)
    R = col.size
    step = max(1, 4_000_000 // max(R, 1))
    for s in range(0, R, step):
        sl = slice(s, min(R, s + step))
        lo = np.maximum(start[sl, None], start[None, :])
        hi = np.minimum(stop[sl, None], stop[None, :])
        ln = np.maximum(hi - lo, 0).astype(float)
        key = col[sl, None] * L + col[None, :]
        hit = ln > 0
        out += np.bincount(key[hit], weights=ln[hit], minlength=L * L)
    return out.reshape(L, L)


def _union(track: np.ndarray, pairs: np.ndarray, overlap: np.ndarray | None = None) -> tuple[np.ndarray, int]:
    """Merge tracks joined by ``pairs`` (N, 2), in order; renumber 0..T'-1 in order of first label.

    With ``overlap`` (the (L, L) frames two labels share), a pair whose
    tracks would then hold two labels seen at the same frame is skipped: one
    marker is never seen twice at once. Returns (new track of every label,
    number of pairs applied).
    """
    T = int(track.max()) + 1 if track.size and track.max() >= 0 else 0
    parent = np.arange(T)
    members: dict[int, list[int]] = {}
    if overlap is not None:
        for lab in np.flatnonzero(track >= 0):
            members.setdefault(int(track[lab]), []).append(int(lab))

    def find(x: int) -> int:
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    applied = 0
    for a, b in np.asarray(pairs, dtype=int).reshape(-1, 2):
        ra, rb = find(a), find(b)
        if ra == rb:
            continue
        if overlap is not None:
            ma, mb = members.get(ra, []), members.get(rb, [])
            if ma and mb and overlap[np.ix_(ma, mb)].any():
                continue
            members[min(ra, rb)] = ma + mb
            members.pop(max(ra, rb), None)
        parent[max(ra, rb)] = min(ra, rb)
        applied += 1
    root = np.array([find(x) for x in range(T)], dtype=int)
    ok = track >= 0
    new = np.full(track.shape, -1)
    r = root[track[ok]]
    uniq, first = np.unique(r, return_index=True)
    rank = np.empty(uniq.size, dtype=int)
    rank[np.argsort(first)] = np.arange(uniq.size)
    new[ok] = rank[np.searchsorted(uniq, r)]
    return new, applied


def _piece_ranges(pieces: list[tuple[int, int]], bridged: np.ndarray) -> list[list[int]]:
    """[start, stop) of the pieces a take was merged in (pieces joined where a label bridges a loss)."""
    out = [[int(pieces[0][0]), int(pieces[0][1])]]
    for i, (a, b) in enumerate(pieces[1:]):
        if bridged[i]:
            out[-1][1] = int(b)
        else:
            out.append([int(a), int(b)])
    return out


def _pieces(vis: np.ndarray) -> list[tuple[int, int]]:
    """Frame ranges [start, stop) separated by interior frames where nothing is seen."""
    any_vis = vis.any(axis=1)
    seen = np.flatnonzero(any_vis)
    if seen.size == 0:
        return []
    v = any_vis[seen[0] : seen[-1] + 1]
    d = np.diff(np.concatenate([[0], v.astype(np.int8), [0]]))
    starts = np.flatnonzero(d == 1) + seen[0]
    stops = np.flatnonzero(d == -1) + seen[0]
    return list(zip(starts.tolist(), stops.tolist()))


def run(markers: Markers, params: Params = Params()) -> Markers:
    """Merge the labels of a passive take into physical markers; drop ghosts, jumps, bad edges.

    Parameters
    ----------
    markers : Markers, usually the output of clean.
    params : Params

    Returns
    -------
    Markers
        ``stage="merge-ids"``, one label per physical marker (points merged,
        never two sources at one frame), ``info["merge_ids"]`` recording which
        labels became which and what was dropped and why;
        ``info["warnings"]`` gains a line when the take had to be handled in
        pieces or labels were left unmatched.

    Raises
    ------
    DataError
        When no marker is left (every label a ghost).
    """
    info = dict(markers.info)
    warnings = list(info.get("warnings", []) or [])
    F, L = markers.points.shape[:2]
    vis0 = visible(markers.points)
    physical = int(vis0.sum(axis=1).max()) if vis0.size else 0
    if not params.enabled or L == 0 or F == 0 or physical == L:
        # physical == L: some frame shows every label at once, so no two labels can be
        # one marker and no label is a ghost (it is seen with all the others); nothing to merge
        info["merge_ids"] = {
            "version": VERSION,
            "enabled": bool(params.enabled),
            "labels_in": L,
            "labels_out": L,
            "physical_markers": physical,
            "looks_relabelled": False,
            "pieces": [],
            "merged": {lab: [lab] for lab in markers.labels},
            "dropped": {"ghost_labels": [], "ghost_samples": 0, "jump_samples": 0, "edge_samples": 0,
                        "emptied_labels": []},
        }
        return replace(markers, stage="merge-ids", info=info)

    p = params
    mg_ = _Merger(markers, p)
    rate = mg_.rate
    labels = markers.labels
    life = mg_.vis.sum(axis=0)

    # 1. ghosts: short-lived and rigid to nothing
    # (attached: rigid to a label over at least half of its life, not for a moment)
    short_frames = min(p.ghost_max_s * rate, 0.25 * int(mg_.vis.any(axis=1).sum()))
    half = np.maximum(mg_.min_shared, 0.5 * life / mg_.sums.stride)
    attached = (mg_.label_partner & (mg_.sums.n >= half[:, None])).any(axis=1)
    ghost = (life < short_frames) & ~attached & (life > 0)
    track = np.where(ghost | (life == 0), -1, 0)
    track[track >= 0] = np.arange(int((track >= 0).sum()))
    vis_ng = mg_.vis & (track >= 0)[None, :]
    physical = int(vis_ng.sum(axis=1).max()) if vis_ng.size else 0

    # pieces: Kirk's failure case (every marker lost at once); no merge across.
    # A label seen on both sides of a loss (active systems keep labels) bridges it.
    pieces = _pieces(vis_ng)
    starts = np.array([s for s, _ in pieces]) if pieces else np.zeros(1, int)
    real = track >= 0
    piece_first = np.searchsorted(starts, mg_.first, side="right") - 1
    piece_last = np.searchsorted(starts, np.maximum(mg_.last, 0), side="right") - 1
    bridged = np.zeros(max(len(pieces) - 1, 0), dtype=bool)
    for a, b in zip(piece_first[real], piece_last[real]):
        bridged[a:b] = True
    piece_group = np.concatenate([[0], np.cumsum(~bridged)]) if pieces else np.zeros(1, int)
    piece_of = np.where(real, piece_group[np.clip(piece_first, 0, len(piece_group) - 1)], -1)
    breaks = [(pieces[i][1], pieces[i + 1][0]) for i in np.flatnonzero(~bridged)]

    max_gap = max(1, int(round(p.max_gap_s * rate)))
    max_speed = p.max_speed_mm_s / rate
    evidence = {"linked": 0, "linked_single_partner": 0, "common_partners": 0, "pose": 0}
    ambiguous = 0

    def allowed(st: _State, pairs: np.ndarray) -> np.ndarray:
        """Pairs of tracks in the same group of pieces."""
        if pairs.size == 0:
            return np.zeros(0, dtype=bool)
        tp = np.full(st.n_tracks, -1)
        ok = st.track >= 0
        tp[st.track[ok]] = piece_of[ok]
        return tp[pairs[:, 0]] == tp[pairs[:, 1]]

    link = dict(n_frames=F, max_gap=max_gap, link_mm=p.link_mm, margin_mm=p.margin_mm, max_speed=max_speed)
    rounds = 0
    for _ in range(max(1, p.max_rounds)):
        # 2. linking rounds (every join gives longer tracks, hence more common partners)
        while rounds < p.max_rounds:
            rounds += 1
            st = mg_.state(track, full=False)
            lk = link_tracks(st.first, st.last, st.p_first, st.p_last, st.mean, st.partner, st.overlap, **link, min_common=2)
            pairs = lk.pairs[allowed(st, lk.pairs)] if lk.pairs.size else lk.pairs
            if pairs.size:
                track, n = _union(track, pairs, mg_.label_overlap)
                evidence["linked"] += n
                continue
            ambiguous = lk.ambiguous
            lk1 = link_tracks(st.first, st.last, st.p_first, st.p_last, st.mean, st.partner, st.overlap, **link, min_common=1)
            prov = lk1.pairs[allowed(st, lk1.pairs)] if lk1.pairs.size else lk1.pairs
            good = _provisional(mg_, st, prov, link, allowed)
            if not good.size:  # whole rigid triangles relabelled at once
                tri = triangle_links(st.first, st.last, st.mean, st.partner, n_frames=F, max_gap=max_gap,
                                     link_mm=p.link_mm, margin_mm=p.margin_mm)
                tri = tri[allowed(st, tri)] if tri.size else tri
                good = _provisional(mg_, st, tri, link, allowed)
            if not good.size:
                break
            track, n = _union(track, track[good], mg_.label_overlap)
            evidence["linked_single_partner"] += n
        # 3. Kirk's clustering of what is left; then link again if it merged anything
        st = mg_.state(track)
        merges, n_sig, n_pose = _cluster(mg_, st, allowed, p)
        evidence["common_partners"] += n_sig
        evidence["pose"] += n_pose
        if not merges.size:
            break
        track, _ = _union(track, merges, mg_.label_overlap)

    # ghosts that looked attached (a still ghost is rigid to every still marker):
    # short tracks that never move and that no physical marker could be (no
    # track that shares a rigid partner with it fits its place)
    st = mg_.state(track)
    t_life = np.bincount(track[track >= 0], weights=life[track >= 0], minlength=st.n_tracks)
    short = t_life < short_frames
    P = st.partner.astype(np.float32)
    cand = ((P @ P) > 0) & (st.overlap == 0) & short[:, None]
    np.fill_diagonal(cand, False)
    ci, cj = np.nonzero(cand)
    cost, _ = common_partner_cost(st.mean, st.partner, ci, cj)
    could_be = np.zeros(st.n_tracks, dtype=bool)
    could_be[ci[cost <= 2 * p.link_mm]] = True
    spread = np.zeros(st.n_tracks)
    has = st.vis.any(axis=0)
    if has.any():
        pts_h = st.points[:, has]
        spread[has] = np.nanmax(np.linalg.norm(pts_h - np.nanmedian(pts_h, axis=0), axis=2), axis=0)
    still = ~(spread > 3 * mg_.rigid_mm)
    late_ghost = short & ~could_be & still
    if late_ghost.any():
        ghost |= (track >= 0) & late_ghost[np.maximum(track, 0)]
        track = np.where(ghost, -1, track)
        track, _ = _union(track, np.zeros((0, 2), dtype=int))
    vis_ng = mg_.vis & (track >= 0)[None, :]
    physical = int(vis_ng.sum(axis=1).max()) if vis_ng.size else 0

    # 4. outliers on the merged markers
    st = mg_.state(track)
    reliable = partners_of(st.mean, st.std, st.n, mg_.rigid_mm,
                           max(mg_.min_shared, int(p.reliable_s * rate / mg_.sums.stride)), st.shared, 0.02)
    max_len = max(1, int(round(p.max_jump_s * rate)))
    jumps, soft = rigid_jumps(st.points, st.vis, st.mean, st.std, reliable, jump_mm=p.jump_mm, step_mm=p.step_mm,
                              max_len=max_len)
    from scipy import ndimage  # here: passive takes only (importing it costs a tenth of a second)

    keep = st.vis & ~jumps
    # doubtful samples within edge_frames of a gap (including the new ones)
    k = max(0, int(p.edge_frames))
    if k:
        inner = ndimage.binary_erosion(keep, structure=np.ones((2 * k + 1, 1), dtype=bool), border_value=1)
        edge = keep & ~inner & soft
    else:
        edge = np.zeros_like(keep)
    keep &= ~edge
    out_pts = np.where(keep[:, :, None], st.points, np.nan)

    # output: tracks with samples left, ordered by their first source label
    T = st.n_tracks
    members = [np.flatnonzero(track == t) for t in range(T)]
    alive = keep.any(axis=0)
    if not alive.any():
        raise DataError(
            "every label is a ghost (short-lived, rigidly attached to nothing), no marker is left — "
            "check that this is the take you meant, or give a longer one", markers.source or None,
        )
    order = sorted((t for t in range(T) if alive[t]), key=lambda t: members[t].min())
    names, merged = [], {}
    for t in order:
        m = members[t]
        best = m[np.argmax(life[m])]  # longest; ties: the first
        names.append(labels[best])
        merged[labels[best]] = [labels[i] for i in m]
    dropped_tracks = [labels[i] for t in range(T) if not alive[t] for i in members[t]]

    extra = len(order) - physical
    new_warnings = []
    if breaks:
        rng_txt = ", ".join(f"{a}–{b - 1}" for a, b in breaks)
        new_warnings.append(
            f"every marker was lost at once (frames {rng_txt}): labels before and after cannot be matched "
            f"(Kirk's failure case), so the take was merged in {len(breaks) + 1} pieces"
        )
    looks_relabelled = L > 1.2 * max(physical, 1)
    if looks_relabelled and extra > 0:
        new_warnings.append(
            f"{extra} label(s) could not be matched to a physical marker ({len(order)} labels left for "
            f"{physical} markers seen at once)"
        )
    info["merge_ids"] = {
        "version": VERSION,
        "enabled": True,
        "labels_in": L,
        "labels_out": len(order),
        "physical_markers": physical,
        "looks_relabelled": bool(looks_relabelled),
        "rigid_mm": mg_.rigid_mm,
        "merged": merged,
        "evidence": evidence,
        "ambiguous_links": int(ambiguous),
        "pieces": _piece_ranges(pieces, bridged) if breaks else [],
        "dropped": {
            "ghost_labels": [labels[i] for i in np.flatnonzero(ghost)],
            "ghost_samples": int(life[ghost].sum()),
            "jump_samples": int(jumps.sum()),
            "edge_samples": int(edge.sum()),
            "emptied_labels": dropped_tracks,
        },
    }
    for w in new_warnings:
        log.warning("merge-ids: %s", w)
    if warnings or new_warnings:
        info["warnings"] = warnings + new_warnings
    return replace(
        markers,
        points=out_pts[:, order] if order else np.zeros((F, 0, 3)),
        labels=tuple(names),
        stage="merge-ids",
        info=info,
    )


def _provisional(m: _Merger, st: _State, prov: np.ndarray, link: dict, allowed) -> np.ndarray:
    """Links with a single common partner (markers of one segment lost together), made sure.

    The provisional links are applied together, and linking with two common
    partners is repeated on top of them until nothing changes (a third marker
    of the segment may only then have two common partners). Each link of the
    set is then kept only if, with all the others applied, its two tracks
    have two common partners at the same distances.

    Returns
    -------
    (N, 2) int, the kept links as pairs of *label* indices.
    """
    if prov.size == 0:
        return np.zeros((0, 2), dtype=int)

    def rep(track: np.ndarray, pairs: np.ndarray) -> np.ndarray:
        """Track pairs -> one label of each."""
        first_label = np.full(int(track.max()) + 1, -1)
        labs = np.flatnonzero(track >= 0)
        first_label[track[labs][::-1]] = labs[::-1]
        return first_label[pairs]

    P = rep(st.track, prov)
    for _ in range(8):
        tr, _ = _union(st.track, st.track[P], m.label_overlap)
        s2 = m.state(tr, full=False)
        lk = link_tracks(s2.first, s2.last, s2.p_first, s2.p_last, s2.mean, s2.partner, s2.overlap, **link, min_common=2)
        pairs = lk.pairs[allowed(s2, lk.pairs)] if lk.pairs.size else lk.pairs
        if pairs.size == 0:
            break
        P = np.concatenate([P, rep(tr, pairs)])
    good = []
    for q in range(len(P)):
        tr, _ = _union(st.track, st.track[np.delete(P, q, axis=0)], m.label_overlap)
        ti, tj = tr[P[q, 0]], tr[P[q, 1]]
        if ti == tj:
            continue
        s2 = m.state(tr, full=False)
        cost, k = common_partner_cost(s2.mean, s2.partner, np.array([ti]), np.array([tj]))
        if k[0] >= 2 and cost[0] <= link["link_mm"] and s2.overlap[ti, tj] == 0:
            good.append(P[q])
    return np.array(good, dtype=int).reshape(-1, 2)


def _cluster(m: _Merger, st: _State, allowed, p: Params) -> tuple[np.ndarray, int, int]:
    """Kirk's clustering with repulsion of the tracks left after linking.

    Returns (merges (N, 2) track pairs, merges by common partners, merges by pose distance).
    """
    T = st.n_tracks
    none = (np.zeros((0, 2), dtype=int), 0, 0)
    if T < 2:
        return none
    seen = st.vis.any(axis=0)
    iu, ju = np.triu_indices(T, 1)
    cand = (st.overlap[iu, ju] == 0) & seen[iu] & seen[ju]
    pairs = np.stack([iu[cand], ju[cand]], axis=1)
    if pairs.size:
        pairs = pairs[allowed(st, pairs)]
    if pairs.size == 0:
        return none
    # common-partner distance
    cost = np.empty(len(pairs))
    k = np.empty(len(pairs), dtype=int)
    step = max(1, 2_000_000 // max(T, 1))
    for s in range(0, len(pairs), step):
        c, kk = common_partner_cost(st.mean, st.partner, pairs[s : s + step, 0], pairs[s : s + step, 1])
        cost[s : s + step], k[s : s + step] = c, kk
    # D: distance in units of its threshold (≤ 1: one marker); far: known to be two markers
    D = np.full(len(pairs), np.inf)
    how = np.zeros(len(pairs), dtype=int)  # 1: common partners, 2: pose
    sig = k >= 2
    D[sig] = cost[sig] / p.link_mm
    how[sig] = 1
    # Kirk's pose distance where partners say nothing: only for tracks that
    # follow each other within the linking gap (a marker's next track comes
    # next), and kept only when clearly the best for both tracks
    gap = time_gaps(st.vis)
    need = ~sig & (gap[pairs[:, 0], pairs[:, 1]] <= max(1, int(round(p.max_gap_s * m.rate))))
    if need.any():
        # cached by the labels of both tracks (the same pairs come back every round)
        members = {}
        for lab in np.flatnonzero(st.track >= 0):
            members.setdefault(int(st.track[lab]), []).append(int(lab))
        keys = [(tuple(members[a]), tuple(members[b])) for a, b in pairs[need]]
        todo = [q for q, key in enumerate(keys) if key not in m.pose_cache]
        if todo:
            new = pose_distance(st.points, st.vis, pairs[need][todo])
            m.pose_cache.update({keys[q]: float(v) for q, v in zip(todo, new)})
        pd = np.array([m.pose_cache[key] for key in keys])
        D[need] = pd / p.pose_mm
        how[need] = 2
        D = np.where((how == 2) & ~_clear_best(pairs, D, st.overlap, p.margin_mm / p.pose_mm), np.inf, D)
    far = np.zeros((T, T), dtype=bool)
    bad = np.isfinite(D) & (D > 1.0)
    far[pairs[bad, 0], pairs[bad, 1]] = far[pairs[bad, 1], pairs[bad, 0]] = True
    use = D <= 1.0
    if not use.any():
        return none
    pairs, D, how = pairs[use], D[use], how[use]
    # connected groups of candidates; spectral clustering with repulsion inside each
    Dm = np.full((T, T), np.inf)
    Dm[pairs[:, 0], pairs[:, 1]] = D
    Dm[pairs[:, 1], pairs[:, 0]] = D
    Hm = np.zeros((T, T), dtype=int)
    Hm[pairs[:, 0], pairs[:, 1]] = how
    Hm[pairs[:, 1], pairs[:, 0]] = how
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(T, T))
    n_comp, comp = connected_components(g, directed=False)
    rng = np.random.default_rng(p.seed)
    merges: list[tuple[int, int]] = []
    n_sig = n_pose = 0
    for c in range(n_comp):
        nodes = np.flatnonzero(comp == c)
        if nodes.size < 2:
            continue
        sub_vis = st.vis[:, nodes]
        kc = int(sub_vis.sum(axis=1).max())
        Dc = Dm[np.ix_(nodes, nodes)]
        A = np.where(np.isfinite(Dc), np.exp(-0.5 * (np.where(np.isfinite(Dc), Dc, 0.0) / 0.5) ** 2), 0.0)
        np.fill_diagonal(A, 1.0)
        R = (st.overlap[np.ix_(nodes, nodes)] > 0).astype(float)
        np.fill_diagonal(R, 0.0)
        lab = repulsion_spectral(A, R, kc, rng=rng) if kc < nodes.size else np.arange(nodes.size)
        # inside each cluster: join by increasing distance, never two tracks seen together
        for cl in np.unique(lab):
            mem = nodes[lab == cl]
            if mem.size < 2:
                continue
            group = {int(t): {int(t)} for t in mem}
            vis_g = {int(t): st.vis[:, t].copy() for t in mem}
            e_i, e_j = np.triu_indices(mem.size, 1)
            dd = Dm[mem[e_i], mem[e_j]]
            for q in np.argsort(dd):
                if not np.isfinite(dd[q]):
                    break
                a, b = int(mem[e_i[q]]), int(mem[e_j[q]])
                ra = next(r for r, s in group.items() if a in s)
                rb = next(r for r, s in group.items() if b in s)
                if ra == rb or (vis_g[ra] & vis_g[rb]).any():
                    continue
                # no pair across the two groups may be known to be two markers
                if far[np.ix_(sorted(group[ra]), sorted(group[rb]))].any():
                    continue
                group[ra] |= group.pop(rb)
                vis_g[ra] |= vis_g.pop(rb)
                merges.append((a, b))
                if Hm[a, b] == 1:
                    n_sig += 1
                else:
                    n_pose += 1
    return np.array(merges, dtype=int).reshape(-1, 2), n_sig, n_pose


def _clear_best(pairs: np.ndarray, D: np.ndarray, overlap: np.ndarray, margin: float) -> np.ndarray:
    """(N,) bool: pair ``(i, j)`` beats by ``margin`` every pair ``(i, j')`` with ``j'`` seen with
    ``j`` and every ``(i', j)`` with ``i'`` seen with ``i`` (the rivals it excludes)."""
    out = np.ones(len(pairs), dtype=bool)
    fin = np.flatnonzero(np.isfinite(D))
    for q in fin:
        i, j = pairs[q]
        for a, b in ((i, j), (j, i)):
            # pairs that contain a, whose other track overlaps b
            other = np.where(pairs[fin, 0] == a, pairs[fin, 1], np.where(pairs[fin, 1] == a, pairs[fin, 0], -1))
            rival = (other >= 0) & (other != b)
            rival[rival] = overlap[b, other[rival]] > 0
            if rival.any() and D[fin][rival].min() < D[q] + margin:
                out[q] = False
    return out
