"""Segments left out of a fitted tree: the joints artifact without them, and what else goes with them.

The joints stage leaves out leaves that ride on nothing of the subject or whose joint cannot be placed;
the rigid stage, segments that are never seen well enough to fit. Their markers are then left out of the
segments (as markers seen too rarely are) and their joints out of the tree.
"""
from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import replace

import numpy as np

from ..artifacts import Joints

__all__ = ["cut_off", "leave_out", "segment_words"]


def segment_words(labels: Sequence[str], name: str) -> str:
    """How a warning names a segment: "marker X" for one marker, else "segment NAME (markers X, Y)"."""
    labels = list(labels)
    return f"marker {labels[0]}" if len(labels) == 1 else f"segment {name} (markers {', '.join(labels)})"


def cut_off(edges: np.ndarray, root: int, n_segments: int, drop: Iterable[int],
            markers: np.ndarray) -> dict[int, int]:
    """The segments that hang on the rest of the tree only through the segments ``drop``: {segment: the
    dropped segment it hung through}.

    ``edges`` (E, 2) (parent, child) directed away from ``root``; ``markers`` (S,) markers per segment.
    Without the dropped segments the tree falls apart; the part kept is the one holding the root (the
    tree's centre), or, when the root itself is dropped, the part with the most markers (then the most
    segments, then the lowest segment). No joint joins the other parts to it: each joint of theirs with
    the kept part was a joint with a dropped segment, and putting one in its place (a shank hung on the
    pelvis where the thigh was left out) would invent a joint whose offsets the data say vary.
    """
    drop = {int(s) for s in drop}
    keep = [s for s in range(n_segments) if s not in drop]
    comp = {s: s for s in keep}

    def find(x: int) -> int:
        while comp[x] != x:
            comp[x] = comp[comp[x]]
            x = comp[x]
        return x

    for a, b in np.asarray(edges, dtype=int).reshape(-1, 2):
        if a not in drop and b not in drop:
            comp[find(int(b))] = find(int(a))
    parts: dict[int, list[int]] = {}
    for s in keep:
        parts.setdefault(find(s), []).append(s)
    if not parts:
        return {}
    if root not in drop:
        main = find(root)
    else:
        main = min(parts, key=lambda r: (-int(np.sum(markers[parts[r]])), -len(parts[r]), min(parts[r])))
    # each part left out hangs through the dropped segment its topmost segment's parent is
    parent = {int(b): int(a) for a, b in np.asarray(edges, dtype=int).reshape(-1, 2)}
    out: dict[int, int] = {}
    for r, members in parts.items():
        if r == main:
            continue
        through = next((parent[s] for s in members if parent.get(s) in drop), None)
        if through is None:  # the dropped root: its child heads this part
            through = next(int(s) for s in drop if any(parent.get(m) == s for m in members))
        for s in members:
            out[s] = int(through)
    return out


def leave_out(joints: Joints, drops: list[tuple[int, int]], said: list[str]) -> Joints:
    """``joints`` without the segments ``drops`` [(segment, one of its edges)]: their markers left out of the
    segments (as markers seen too rarely are), every joint of theirs out of the tree, the rest renumbered;
    ``said`` the warnings. What is left must be one tree (leaves, or a segment with the parts
    :func:`cut_off` finds); its root stays, or, when it is left out, the kept segment without a parent."""
    topo = joints.topology
    seg = topo.segments
    labels = seg.markers.labels
    drop = sorted({int(s_) for s_, _ in drops})
    keep_s = np.array([s_ for s_ in range(seg.n_segments) if s_ not in drop])
    new_of = np.full(seg.n_segments, -1, dtype=int)
    new_of[keep_s] = np.arange(keep_s.size)
    group = np.where(seg.group >= 0, new_of[np.maximum(seg.group, 0)], -1)
    gone = [labels[int(i)] for s_ in drop for i in seg.members(s_)]
    seg_info = dict(seg.info, left_out=list(seg.info.get("left_out", [])) + gone, n_segments=int(keep_s.size))
    if isinstance(seg.info.get("groups"), list) and len(seg.info["groups"]) == seg.n_segments:
        seg_info["groups"] = [g for s_, g in enumerate(seg.info["groups"]) if s_ not in drop]
    new_seg = replace(seg, group=group, info=seg_info)
    keep_e = np.array([e for e, (a, b) in enumerate(topo.edges) if a not in drop and b not in drop], dtype=int)
    edges = new_of[topo.edges[keep_e]].reshape(-1, 2)
    if topo.root not in drop:
        root = int(new_of[topo.root])
    else:
        children = set(edges[:, 1].tolist())
        root = next(s_ for s_ in range(keep_s.size) if s_ not in children)
    topo_info = dict(topo.info)
    if isinstance(topo_info.get("own_floor_mm2"), list) and len(topo_info["own_floor_mm2"]) == seg.n_segments:
        topo_info["own_floor_mm2"] = [topo_info["own_floor_mm2"][s_] for s_ in keep_s]
    new_topo = replace(topo, segments=new_seg, edges=edges, cost=topo.cost[keep_e],
                       pair_cost=topo.pair_cost[np.ix_(keep_s, keep_s)], root=root, info=topo_info)
    info = dict(joints.info, per_joint=[joints.info["per_joint"][e] for e in keep_e],
                warnings=list(joints.info.get("warnings", [])) + said)
    if "alt_start" in info:
        old_to_new = {int(e): i for i, e in enumerate(keep_e)}
        info["alt_start"] = [old_to_new[e] for e in info["alt_start"] if e in old_to_new]
    alt = None if joints.alt_centres is None else joints.alt_centres[:, keep_e]
    return replace(joints, topology=new_topo, centres=joints.centres[:, keep_e],
                   method=tuple(joints.method[e] for e in keep_e), residual=joints.residual[keep_e],
                   info=info, alt_centres=alt)
