"""Fitted skeletons compared: their trees matched bone to bone and the distance between their proportions."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError

#: Two skeletons whose proportion distance (percent) is at most this are "likely" the same
#: subject; it is also the smallest distance at which automatic clustering separates subjects.
SAME_SUBJECT_PCT = 0.5
#: With at least this many bones compared, the worst one is left out of the distance.
TRIM_MIN_BONES = 5


_REPORT_FIX = "give the JSON written by 'fit --report' or 'batch', unedited"


@dataclass(frozen=True)
class Bones:
    """A fitted skeleton's tree and bone lengths, from a report's ``bones`` (and ``segments``).

    Attributes
    ----------
    names : tuple of str
        Segment names.
    parent : (S,) int ndarray
        Parent segment, -1 for the root (the tree's centre, as the fit chose it).
    length : (S,) float ndarray
        Bone length in mm (NaN where the report has none).
    labels : tuple of frozenset of str
        Marker labels of each segment (empty when the report does not say).
    source : str
        Where the report came from (for messages).
    """

    names: tuple[str, ...]
    parent: np.ndarray
    length: np.ndarray
    labels: tuple[frozenset[str], ...]
    source: str = ""

    @classmethod
    def from_report(cls, report: dict, source: str = "") -> Bones:
        """Read ``report["bones"]`` (``segment``, ``parent``, ``length_mm``).

        Raises
        ------
        InputError
            Not a fit report, or its bones do not form one tree.
        """
        bones = report.get("bones") if isinstance(report, dict) else None
        if not isinstance(bones, list) or not bones:
            raise InputError("not a fit report (no 'bones') — give the JSON written by 'fit --report' or 'batch'", source or None)
        try:
            names = tuple(str(b["segment"]) for b in bones)
            parents = [b.get("parent") for b in bones]
            lengths = [b.get("length_mm") for b in bones]
        except (KeyError, TypeError, AttributeError):
            raise InputError("damaged report: every bone needs 'segment', 'parent' and 'length_mm' — " + _REPORT_FIX, source or None) from None
        index = {n: i for i, n in enumerate(names)}
        if len(index) != len(names):
            raise InputError("damaged report: repeated segment names in 'bones' — " + _REPORT_FIX, source or None)
        try:
            parent = np.array([-1 if p is None else index[str(p)] for p in parents], dtype=int)
        except (KeyError, TypeError) as e:
            raise InputError(f"damaged report: bone parent {str(e.args[0])[:40]!r} is not a segment — {_REPORT_FIX}", source or None) from None
        bad = [x for x in lengths if x is not None and (isinstance(x, bool) or not isinstance(x, (int, float))
                                                         or not 0 <= float(x) <= 1e7)]
        if bad:
            raise InputError(f"damaged report: bone length {str(bad[0])[:40]!r} is not a length in mm (0 to 1e7)"
                             f" — {_REPORT_FIX}", source or None)
        length = np.array([np.nan if x is None else float(x) for x in lengths], dtype=float)
        if np.count_nonzero(parent < 0) != 1 or not _is_tree(parent):
            raise InputError(f"damaged report: the bones do not form one tree — {_REPORT_FIX}", source or None)
        seg_labels = {}
        segments = report.get("segments")
        for s in segments if isinstance(segments, list) else []:
            if isinstance(s, dict) and "name" in s and isinstance(s.get("markers"), list):
                seg_labels[str(s["name"])] = frozenset(str(m) for m in s["markers"])
        labels = tuple(seg_labels.get(n, frozenset()) for n in names)
        return cls(names, parent, length, labels, source)

    @property
    def n(self) -> int:
        return len(self.names)

    @property
    def root(self) -> int:
        return int(np.flatnonzero(self.parent < 0)[0])

    def children(self) -> list[list[int]]:
        kids: list[list[int]] = [[] for _ in range(self.n)]
        for s, p in enumerate(self.parent.tolist()):
            if p >= 0:
                kids[p].append(s)
        return kids

    @property
    def inner(self) -> np.ndarray:
        """(S,) bool: segments with children, whose bone runs joint to joint (a leaf's runs to its End Site)."""
        m = np.zeros(self.n, dtype=bool)
        m[self.parent[self.parent >= 0]] = True
        return m

    def canonical(self) -> list[str]:
        """Canonical form of every rooted subtree (AHU encoding: equal strings ⇔ isomorphic subtrees)."""
        kids = self.children()
        out = [""] * self.n
        for s in _postorder(kids, self.root):
            out[s] = "(" + "".join(sorted(out[c] for c in kids[s])) + ")"
        return out

    @property
    def topology(self) -> str:
        """Canonical form of the whole tree, rooted where the fit rooted it."""
        return self.canonical()[self.root]


def _is_tree(parent: np.ndarray) -> bool:
    n = parent.size
    for s in range(n):
        seen, p = 0, s
        while p >= 0:
            p = int(parent[p])
            seen += 1
            if seen > n:
                return False
    return True


def _postorder(kids: list[list[int]], root: int) -> list[int]:
    order, stack = [], [root]
    while stack:
        s = stack.pop()
        order.append(s)
        stack.extend(kids[s])
    return order[::-1]


def _proportions(b: Bones) -> np.ndarray:
    """Lengths of the inner bones over their total (NaN elsewhere); for the cost of a tree match."""
    ok = b.inner & np.isfinite(b.length) & (b.length > 0)
    p = np.full(b.n, np.nan)
    if ok.any():
        p[ok] = b.length[ok] / b.length[ok].sum()
    return p


def _label_match(a: Bones, b: Bones) -> np.ndarray | None:
    """b's segment for each of a's, by marker labels, if that is a tree isomorphism (same root)."""
    if a.n != b.n or not all(a.labels) or not all(b.labels):
        return None
    index = {lab: j for j, lab in enumerate(b.labels)}
    if len(index) != b.n or len(set(a.labels)) != a.n:
        return None
    try:
        m = np.array([index[lab] for lab in a.labels], dtype=int)
    except KeyError:
        return None
    for i, p in enumerate(a.parent.tolist()):
        q = int(b.parent[m[i]])
        if (p < 0) != (q < 0) or (p >= 0 and m[p] != q):
            return None
    return m


def _tree_match(a: Bones, b: Bones) -> np.ndarray | None:
    """b's segment for each of a's by the tree structure; among equivalent subtrees (left/right limbs),
    the assignment whose proportions differ least. None if the rooted trees differ."""
    from scipy.optimize import linear_sum_assignment

    ca, cb = a.canonical(), b.canonical()
    if ca[a.root] != cb[b.root]:
        return None
    pa, pb = _proportions(a), _proportions(b)
    ka, kb = a.children(), b.children()
    memo: dict[tuple[int, int], tuple[float, list[tuple[int, int]]]] = {}

    def cost(u: int, v: int) -> float:
        x, y = pa[u], pb[v]
        if not (np.isfinite(x) and np.isfinite(y)):
            return 0.0
        return float((x - y) ** 2 / max((x + y) / 2, 1e-12))

    def rec(u: int, v: int) -> tuple[float, list[tuple[int, int]]]:
        if (u, v) in memo:
            return memo[(u, v)]
        total, pairs = cost(u, v), [(u, v)]
        groups: dict[str, tuple[list[int], list[int]]] = {}
        for c in ka[u]:
            groups.setdefault(ca[c], ([], []))[0].append(c)
        for c in kb[v]:
            groups[cb[c]][1].append(c)
        for xs, ys in groups.values():
            if len(xs) == 1:
                sub = [rec(xs[0], ys[0])]
            else:
                C = np.array([[rec(x, y)[0] for y in ys] for x in xs])
                r, c = linear_sum_assignment(C)
                sub = [rec(xs[i], ys[j]) for i, j in zip(r, c)]
            for t, p in sub:
                total += t
                pairs += p
        memo[(u, v)] = (total, pairs)
        return memo[(u, v)]

    _, pairs = rec(a.root, b.root)
    m = np.full(a.n, -1, dtype=int)
    for u, v in pairs:
        m[u] = v
    return m


def match_bones(a: Bones, b: Bones) -> tuple[np.ndarray, str] | None:
    """Which segment of ``b`` is each segment of ``a``.

    By the segments' marker labels when both skeletons have the same label
    sets and these give the same tree; otherwise by the tree structure, rooted
    where each fit rooted it (subtrees matched by canonical form, equivalent
    siblings — left and right limbs — paired so that their proportions differ
    least).

    Returns
    -------
    (mapping, how) or None
        ``mapping`` (S,) int ndarray: ``b``'s index for each of ``a``'s
        segments; ``how`` is ``"labels"`` or ``"tree"``. None when the
        topologies differ.
    """
    m = _label_match(a, b)
    if m is not None:
        return m, "labels"
    m = _tree_match(a, b)
    return (m, "tree") if m is not None else None


@dataclass
class Comparison:
    """How alike two fitted skeletons are (see :func:`compare_bones`).

    Attributes
    ----------
    a, b : Bones
    mapping : (S,) int ndarray or None
        ``b``'s segment for each of ``a``'s; None when the topologies differ.
    matched_by : str
        ``"labels"``, ``"tree"`` or ``""``.
    used : (S,) bool ndarray
        Bones (of ``a``, matched) that enter the distance.
    relative_difference : (S,) float ndarray
        Per bone, (proportion in b − proportion in a) / their mean, NaN where unused.
    distance_pct : float
        Proportion distance in percent (NaN if it cannot be computed).
    scale : float
        Total length of the bones kept in ``b`` over that in ``a``.
    threshold_pct : float
        The same-subject threshold used for ``same_subject``.
    left_out : int
        The bone (of ``a``) left out of the distance as the worst, -1 if none.
    """

    a: Bones
    b: Bones
    mapping: np.ndarray | None
    matched_by: str
    used: np.ndarray
    relative_difference: np.ndarray
    distance_pct: float
    scale: float
    threshold_pct: float = SAME_SUBJECT_PCT
    left_out: int = -1

    @property
    def same_subject(self) -> bool:
        """True when the proportions agree within the threshold."""
        return bool(np.isfinite(self.distance_pct) and self.distance_pct <= self.threshold_pct)


def _weighted_rms(la: np.ndarray, lb: np.ndarray, keep: np.ndarray) -> tuple[float, np.ndarray]:
    pa, pb = la / la[keep].sum(), lb / lb[keep].sum()
    m = (pa + pb) / 2
    r = (pb - pa) / m
    return float(np.sqrt(np.sum(m[keep] * r[keep] ** 2) / np.sum(m[keep])) * 100.0), r


def proportion_distance(la: np.ndarray, lb: np.ndarray, trim: bool = True) -> tuple[float, np.ndarray, int]:
    """Distance between the proportions of two sets of matched bone lengths.

    Each set is normalised by its total (``p = L / ΣL``); with ``m`` the mean
    of the two proportions and ``r = (p_b − p_a) / m`` the relative difference
    of each bone, the distance is the ``m``-weighted RMS of ``r``,
    ``sqrt(Σ m r² / Σ m)``, in percent: long bones weigh more, as their
    relative lengths are better determined, and overall size does not count.

    One badly fitted joint spoils two bones' lengths and, through the total,
    every proportion; so with ``trim`` and at least :data:`TRIM_MIN_BONES`
    bones, the bone with the largest contribution ``m r²`` is left out and the
    distance computed again over the others, normalised by their own total.

    Parameters
    ----------
    la, lb : (K,) array_like
        Matched bone lengths (mm), finite and positive, K ≥ 2.
    trim : bool
        Leave out the worst bone (see above).

    Returns
    -------
    distance_pct : float
    relative_difference : (K,) ndarray
        ``r`` per bone (a fraction), with the normalisation of the bones kept.
    left_out : int
        Index of the bone left out, -1 if none.
    """
    la, lb = np.asarray(la, float), np.asarray(lb, float)
    keep = np.ones(la.size, dtype=bool)
    d, r = _weighted_rms(la, lb, keep)
    if not trim or la.size < TRIM_MIN_BONES:
        return d, r, -1
    pa, pb = la / la.sum(), lb / lb.sum()
    worst = int(np.argmax((pa + pb) / 2 * r**2))
    keep[worst] = False
    d, r = _weighted_rms(la, lb, keep)
    return d, r, worst


def compare_bones(a: Bones, b: Bones, threshold_pct: float = SAME_SUBJECT_PCT) -> Comparison:
    """Compare two fitted skeletons' proportions.

    The bones compared are the joint-to-joint ones (segments with children)
    whose length is known in both skeletons: an End Site's length depends on
    where the markers were put, not on the subject. When fewer than two such
    bones match (a three-rod linkage), every matched bone with a length is used.
    """
    S = a.n
    nan = np.full(S, np.nan)
    mm = match_bones(a, b)
    if mm is None:
        return Comparison(a, b, None, "", np.zeros(S, bool), nan, float("nan"), float("nan"), threshold_pct)
    m, how = mm
    la, lb = a.length, b.length[m]
    known = np.isfinite(la) & np.isfinite(lb) & (la > 0) & (lb > 0)
    used = known & a.inner
    if used.sum() < 2:
        used = known
    rel = nan.copy()
    if used.sum() < 2:
        return Comparison(a, b, m, how, used, rel, float("nan"), float("nan"), threshold_pct)
    idx = np.flatnonzero(used)
    d, r, worst = proportion_distance(la[idx], lb[idx])
    rel[idx] = r
    left_out = int(idx[worst]) if worst >= 0 else -1
    kept = used.copy()
    if left_out >= 0:
        kept[left_out] = False
    return Comparison(a, b, m, how, used, rel, d, float(lb[kept].sum() / la[kept].sum()), threshold_pct, left_out)


def compare_reports(a: dict, b: dict, threshold_pct: float = SAME_SUBJECT_PCT, sources: tuple[str, str] = ("", "")) -> Comparison:
    """:func:`compare_bones` on two fit reports (dicts as read from their JSON)."""
    return compare_bones(Bones.from_report(a, sources[0]), Bones.from_report(b, sources[1]), threshold_pct)
