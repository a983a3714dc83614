"""The skeleton's soft ties between joints, as rows of one linear system held to zero: each factor whose residual
is linear in the bones' offsets and the markers' (like limbs' bone lengths, a plane of symmetry, a limb's middle joint
in line with its neighbours). :func:`~mocapskel.solvers.model.calibrate.refine_skeleton` adds ``|T g|^2`` to its
objective, ``g`` its constant unknowns."""
from __future__ import annotations

import numpy as np


def tie_rows(pr, d: np.ndarray, like_bones=None, planes=None, lines=None) -> np.ndarray:
    """(n, ng) rows ``T`` over the constant unknowns of ``pr`` (a :class:`~mocapskel.solvers.model.calibrate._Problem`),
    ``d`` (S, 3) the bones' offsets at the start (like bones' lengths are linearised along them); the factors as
    :func:`~mocapskel.solvers.model.calibrate.refine_skeleton` takes them."""
    ng, parent, marker_segment = pr.ng, pr.parent, pr.seg
    # like bones: rows sqrt(w) (u_a . d_a - u_b . d_b), held to 0
    trows = []
    for a, b, w in like_bones or ():
        if parent[a] < 0 or parent[b] < 0 or not w > 0:
            continue
        row = np.zeros(ng)
        for c, sign in ((a, 1.0), (b, -1.0)):
            n = float(np.linalg.norm(d[c]))
            if n > 0:
                row[pr.gi[c] : pr.gi[c] + 3] = sign * d[c] / n
        trows.append(np.sqrt(w) * row)
    for kids, n, w in planes or ():  # rows sqrt(w) n . (mean joint - the parent's marker centroid)
        row, ms = np.zeros(ng), [int(m) for m in pr.used if marker_segment[m] == parent[kids[0]]]
        for c in kids:
            row[pr.gi[c] : pr.gi[c] + 3] += n / len(kids)
        for m in ms:
            row[pr.gl[m] : pr.gl[m] + 3] -= n / len(ms)
        trows.append(np.sqrt(w) * row if ms and w > 0 else 0.0 * row)
    for k, j, u, t, w in lines or ():
        if parent[k] < 0 or parent[j] != k or not w > 0:
            continue
        row = np.zeros(ng)
        row[pr.gi[k] : pr.gi[k] + 3] = (1.0 - t) * np.asarray(u, dtype=float)
        row[pr.gi[j] : pr.gi[j] + 3] = -t * np.asarray(u, dtype=float)
        trows.append(np.sqrt(w) * row)
    return np.array(trows).reshape(-1, ng)
