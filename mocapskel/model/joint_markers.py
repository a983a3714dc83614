"""Virtual joint markers: a solved skeleton's joint centres as named points, to write beside the markers."""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..artifacts import Markers, Motion
from .kinematics import segment_origins
from .naming import generic

_METHOD_TEXT = {
    "score": "SCoRE (functional, linear least squares)",
    "score-hinge": "SCoRE on a hinge-like joint (centre on its axis)",
    "sphere": "a sphere fit (Knight's unbiased MGDK)",
    "jmv": "joint-marker-variance optimisation (Hang 2015)",
    "mtb": "marker-trajectory bases (Hang 2015)",
}


def joint_marker_names(motion: Motion, naming=None) -> list[str]:
    """Names of the virtual joint markers, one per joint (non-root segment, in segment order).

    ``<parent>_<child>_JC`` after the segments it joins, or after the joint
    for a skeleton named as a person (``LeftKnee_JC``; see :mod:`mocapskel.model.naming`).
    """
    sk = motion.skeleton
    if naming is None:
        naming = generic(sk)
    return [f"{naming.joint_names[s]}_JC" for s in range(len(sk.names)) if sk.parent[s] >= 0]


def joint_points(motion: Motion, naming=None) -> tuple[list[str], list[str], np.ndarray]:
    """The virtual joint markers: labels, descriptions and (F, E, 3) lab positions (mm).

    A description names the joint, the two segments it joins (with their
    markers) and how the joints stage found its centre.
    """
    sk = motion.skeleton
    kids = [s for s in range(len(sk.names)) if sk.parent[s] >= 0]
    labels = joint_marker_names(motion, naming)
    seg_names = naming.names if naming is not None else sk.names
    method = {}
    j = sk.joints
    if j is not None:
        for e, (a, b) in enumerate(j.topology.edges.tolist()):
            method[frozenset((a, b))] = j.method[e]
    mseg = np.asarray(sk.marker_segment)
    desc = []
    for s in kids:
        p = int(sk.parent[s])
        how = method.get(frozenset((p, s)))
        mk = lambda q: " ".join(sk.labels[m] for m in np.flatnonzero(mseg == q)[:6])  # noqa: E731
        desc.append(
            f"mocapskel joint centre between {seg_names[p]} ({mk(p)}) and {seg_names[s]} ({mk(s)}), "
            + (f"found by {_METHOD_TEXT.get(how, how)}" if how else "from the subject's skeleton")
        )
    return labels, desc, segment_origins(motion)[:, kids]


def with_joint_markers(markers: Markers, motion: Motion, naming=None) -> Markers:
    """The input markers plus one virtual marker per joint centre per frame (for biomechanics tools)."""
    names, _, jp = joint_points(motion, naming)
    taken = set(markers.labels)
    names = [n if n not in taken else f"{n}_{i}" for i, n in enumerate(names)]
    pts = np.concatenate([markers.points, jp], axis=1)
    info = dict(markers.info)
    info["virtual_joint_markers"] = names
    return replace(markers, points=pts, labels=tuple(markers.labels) + tuple(names), info=info)
