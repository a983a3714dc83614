"""Subjects of a batch: its takes grouped by topology, then clustered by their skeletons' proportions."""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from .proportions import SAME_SUBJECT_PCT, Bones, compare_bones

#: Automatic clustering: the distance between subjects must be at least this many times
#: the spread within them (the largest merge below the cut).
GAP_RATIO = 1.5
#: The spread within a subject is never taken below this (percent): measurement noise.
SPREAD_FLOOR_PCT = 0.25


@dataclass
class SubjectResult:
    """Subjects found in a batch.

    Attributes
    ----------
    labels : list of str
        Per take, ``"S1"``, ``"S2"`` … (numbered in order of first take), or
        ``""`` for a take without a skeleton.
    groups : list of list of int
        Takes (indices) of each topology; subjects are only found within one.
    distances : list of (n, n) ndarray
        Proportion distance (percent) between the takes of each group.
    how : list of str
        How each group's count was chosen (``"given"``, ``"gap"``, ``"threshold"``, ``"single"``).
    warnings : list of str
    """

    labels: list[str]
    groups: list[list[int]] = field(default_factory=list)
    distances: list[np.ndarray] = field(default_factory=list)
    how: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)

    @property
    def n_subjects(self) -> int:
        return len({s for s in self.labels if s})


def choose_clusters(heights: np.ndarray, threshold_pct: float = SAME_SUBJECT_PCT, gap_ratio: float = GAP_RATIO,
                    floor_pct: float = SPREAD_FLOOR_PCT) -> tuple[int | None, str]:
    """The number of subjects from the merge heights of an average-linkage dendrogram.

    Cutting the dendrogram into ``k`` clusters leaves a *spread* (the highest
    merge below the cut, at least ``floor_pct``: the measurement noise) and a
    *separation* (the lowest merge above it). A cut is acceptable when the
    separation exceeds ``threshold_pct`` and is at least ``gap_ratio`` times
    the spread; the acceptable cut with the largest ratio wins (``"gap"``).
    Without one, the dendrogram is cut at ``threshold_pct`` (returns None,
    ``"threshold"``).

    Parameters
    ----------
    heights : (n-1,) ndarray
        Merge distances (percent), ascending.

    Returns
    -------
    k : int or None
    how : str
    """
    h = np.sort(np.asarray(heights, float))
    n = h.size + 1
    best, best_k = 0.0, None
    for k in range(2, n + 1):
        sep = h[n - k]
        spread = h[n - k - 1] if k < n else 0.0
        ratio = sep / max(spread, floor_pct)
        if sep > threshold_pct and ratio >= gap_ratio and ratio > best:
            best, best_k = ratio, k
    return (best_k, "gap") if best_k is not None else (None, "threshold")


def identify_subjects(
    reports: Sequence[dict | None],
    n_subjects: int | None = None,
    *,
    threshold_pct: float = SAME_SUBJECT_PCT,
) -> SubjectResult:
    """Group takes by subject from their skeletons' proportions (Kirk et al. 2005, §5).

    Takes are grouped by topology first (rooted tree); within a group the
    proportion distance (:func:`compare_bones`) of every pair is clustered by
    average linkage. ``n_subjects`` fixes the count when every take shares
    one topology (with several topologies it is ignored, with a warning);
    otherwise the count is chosen by :func:`choose_clusters`.

    Parameters
    ----------
    reports : sequence of dict or None
        Fit reports, None for a take that failed.
    n_subjects : int, optional
    threshold_pct : float
        Same-subject threshold (percent).

    Returns
    -------
    SubjectResult
    """
    from scipy.cluster.hierarchy import fcluster, linkage
    from scipy.spatial.distance import squareform

    n = len(reports)
    bones: list[Bones | None] = []
    warnings: list[str] = []
    for i, rep in enumerate(reports):
        if rep is None:
            bones.append(None)
            continue
        try:
            bones.append(Bones.from_report(rep, f"take {i + 1}"))
        except InputError as e:
            bones.append(None)
            warnings.append(f"no subject for take {i + 1}: {e}")
    groups: dict[str, list[int]] = {}
    for i, b in enumerate(bones):
        if b is not None:
            groups.setdefault(b.topology, []).append(i)
    glist = sorted(groups.values(), key=lambda g: g[0])
    if n_subjects is not None and len(glist) > 1:
        warnings.append(f"--subjects {n_subjects} ignored: the takes have {len(glist)} different topologies "
                        "(subjects are chosen automatically within each)")
    cluster_of: dict[int, tuple[int, int]] = {}
    dists, hows = [], []
    for gi, g in enumerate(glist):
        m = len(g)
        D = np.zeros((m, m))
        for x in range(m):
            for y in range(x + 1, m):
                c = compare_bones(bones[g[x]], bones[g[y]], threshold_pct)  # type: ignore[arg-type]
                d = c.distance_pct if np.isfinite(c.distance_pct) else 0.0
                D[x, y] = D[y, x] = d
        dists.append(D)
        if m == 1:
            lab, how = np.array([1]), "single"
        else:
            Z = linkage(squareform(D, checks=False), method="average")
            if n_subjects is not None and len(glist) == 1:
                k, how = min(n_subjects, m), "given"
            else:
                k, how = choose_clusters(Z[:, 2], threshold_pct)
            if k is None:
                lab = fcluster(Z, t=threshold_pct, criterion="distance")
            else:
                lab = fcluster(Z, t=k, criterion="maxclust")
        hows.append(how)
        for x, i in enumerate(g):
            cluster_of[i] = (gi, int(lab[x]))
    names: dict[tuple[int, int], str] = {}
    labels = []
    for i in range(n):
        if i not in cluster_of:
            labels.append("")
            continue
        key = cluster_of[i]
        if key not in names:
            names[key] = f"S{len(names) + 1}"
        labels.append(names[key])
    return SubjectResult(labels, glist, dists, hows, warnings)
