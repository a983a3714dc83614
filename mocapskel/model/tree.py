"""A skeleton's tree: the order its joints are listed in, joint names a BVH file takes, and like limbs."""
from __future__ import annotations

import re
from collections.abc import Sequence

import numpy as np

from ..artifacts import NAME_PATTERN, check_names  # noqa: F401 (the names' rule lives with the artifacts that hold them)


def depth_first_order(parent: np.ndarray) -> np.ndarray:
    """The order in which a BVH file lists the joints of a tree.

    Parameters
    ----------
    parent : (S,) int array_like
        -1 for the root(s); any numbering (parents need not come first).

    Returns
    -------
    order : (S,) int ndarray
        Joint indices depth first from the root, children in index order, so
        every parent comes before its children. It is ``arange(S)`` when the
        skeleton is already in that order, as every skeleton :func:`~mocapskel.io.bvh_read.read_bvh`
        returns is.
    """
    parent = np.asarray(parent, dtype=np.int64)
    children: list[list[int]] = [[] for _ in range(len(parent))]
    for s in range(len(parent)):
        if parent[s] >= 0:
            children[parent[s]].append(s)
    out: list[int] = []
    stack = [int(r) for r in np.flatnonzero(parent < 0)[::-1]]
    while stack:
        s = stack.pop()
        out.append(s)
        stack.extend(reversed(children[s]))
    return np.asarray(out, dtype=np.int64)


def _clashes(name: str, others: Sequence[str]) -> bool:
    return any(o.startswith(name) or name.startswith(o) for o in others)


def sanitize_names(names: Sequence[str]) -> list[str]:
    """Turn any list of strings into valid BVH joint names (see :func:`check_names`).

    Characters outside ``[A-Za-z0-9_]`` become ``_``; an empty name becomes
    ``joint``; a leading digit gets a ``_`` in front. Duplicates are all
    numbered (``A, A`` -> ``A_1, A_2``; zero-padded so the numbers are not
    prefixes of each other). A name that is a prefix of another gets a suffix
    (``Hip, Hips`` -> ``Hip_1, Hips``): the first of ``_1, _2, ...`` that
    clashes with no other name, else a single character that no other name
    continues it with. Names that are already valid and clash with nothing
    are kept.

    Parameters
    ----------
    names : sequence of str, length S

    Returns
    -------
    list of str, length S
    """
    out = []
    for n in names:
        n = re.sub(r"[^A-Za-z0-9_]", "_", str(n))
        if not n:
            n = "joint"
        if n[0].isdigit():
            n = "_" + n
        out.append(n)
    while True:
        srt = sorted(set(out))
        counts: dict[str, int] = {}
        for n in out:
            counts[n] = counts.get(n, 0) + 1
        # the shortest name that equals or prefixes another: no other name prefixes it
        bad = [a for a, b in zip(srt, srt[1:]) if b.startswith(a)] + [n for n, c in counts.items() if c > 1]
        if not bad:
            return out
        name = min(bad, key=lambda n: (len(n), n))
        where = [i for i, n in enumerate(out) if n == name]
        if len(where) > 1:
            width = len(str(len(where)))
            for k, i in enumerate(where, 1):
                out[i] = f"{name}_{k:0{width}d}"
            continue
        others = [n for n in out if n != name]
        for k in range(1, len(out) + 2):
            cand = f"{name}_{k}"
            if not _clashes(cand, others):
                break
        else:  # every "_k" is taken or prefixed by another name: one free next character
            used = {o[len(name)] for o in others if o.startswith(name) and len(o) > len(name)}
            free = [c for c in "_0123456789abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ" if c not in used]
            cand = name + (free[0] if free else "_")  # no free character: go one deeper next round
        out[where[0]] = cand


def like_limb_pairs(parent: np.ndarray) -> list[tuple[int, int, int]]:
    """``(segment, its like, k)`` down every pair of like limbs (:func:`like_chains`), ``k`` counting from the
    chains' first segments."""
    return [(s_a, s_b, k) for a, b in like_chains(parent)
            for k, (s_a, s_b) in enumerate(zip(limb_chains(parent, a), limb_chains(parent, b)))]


def unlike_bones(skel, pairs: list[tuple[int, int]], tol: float) -> list[tuple[int, int, float, float]]:
    """Of the segment pairs ``(a, b)``, those whose bones (each to its one child joint; a limb's end has none)
    differ by more than ``tol`` of the shorter: ``(a, b, length of a's, length of b's)``."""
    parent = np.asarray(skel.parent)
    off = np.linalg.norm(skel.offset, axis=1)
    out = []
    for a, b in pairs:
        kids = [np.flatnonzero(parent == s) for s in (a, b)]
        if any(k.size != 1 for k in kids):
            continue  # a limb's end: no bone to the next joint
        la, lb = float(off[kids[0][0]]), float(off[kids[1][0]])
        if la > 0 and lb > 0 and max(la, lb) > (1.0 + tol) * min(la, lb):
            out.append((a, b, la, lb))
    return out


def limb_chains(parent: np.ndarray, s: int) -> list[int]:
    """Segment ``s`` and its descendants down a chain (while each has one child)."""
    out = [int(s)]
    while (kids := np.flatnonzero(parent == out[-1])).size == 1:
        out.append(int(kids[0]))
    return out


def like_chains(parent: np.ndarray) -> list[tuple[int, int]]:
    """Pairs of children of one segment that are chains of the same length, two segments or more."""
    out = []
    for p in range(len(parent)):
        kids = [int(k) for k in np.flatnonzero(parent == p)]
        chains = {c: limb_chains(parent, c) for c in kids}
        for i, a in enumerate(kids):
            for b in kids[i + 1:]:
                ca, cb = chains[a], chains[b]
                if len(ca) == len(cb) >= 2 and all(not (parent == x).any() for x in (ca[-1], cb[-1])):
                    out.append((a, b))
    return out


def like_subtrees(parent: np.ndarray, count: np.ndarray) -> list[tuple[int, int, int]]:
    """(parent, a, b) for every two children of one segment that are like limbs: subtrees of the same
    shape, segment for segment as many markers (``count``), each of two segments or more (two legs,
    two arms; not a head and an arm). By parent, then in child order. Stricter than :func:`like_chains`, which
    compares the chains' lengths only."""
    parent = np.asarray(parent)
    out = []
    for p in range(len(parent)):
        kids = [int(k) for k in np.flatnonzero(parent == p)]
        shape = {c: subtree_shape(parent, count, c) for c in kids}
        out += [(p, a, b) for i, a in enumerate(kids) for b in kids[i + 1:] if shape[a] == shape[b] and shape[a][1]]
    return out


def subtree_shape(parent: np.ndarray, count: np.ndarray, s: int) -> tuple:
    """A canonical form of the subtree below segment ``s``: its marker count and its children's
    forms, sorted."""
    return (int(count[s]), tuple(sorted(subtree_shape(parent, count, int(k)) for k in np.flatnonzero(parent == s))))


def tree_from(parent: np.ndarray, root: int) -> np.ndarray:
    """The parent array of the same tree rooted at ``root``."""
    S = len(parent)
    nb: list[list[int]] = [[] for _ in range(S)]
    for s, p in enumerate(parent.tolist()):
        if p >= 0:
            nb[s].append(p)
            nb[p].append(s)
    new = np.full(S, -2, dtype=np.int64)
    new[root] = -1
    stack = [root]
    while stack:
        s = stack.pop()
        for n in sorted(nb[s]):
            if new[n] == -2:
                new[n] = s
                stack.append(n)
    return new
