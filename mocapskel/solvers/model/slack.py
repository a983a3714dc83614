"""How far a take's joints wander about their fixed places: a variance component measured at a rigid fit.

A joint that wanders by sigma per axis from frame to frame (a segment's markers moving together on the skin) leaves
at a rigid fit, in each frame, a least-squares offset e_f of the joint from its fixed place (that frame's pose free
with it) with E|e_f|^2 = 3 sigma^2 + sigma_n^2 tr(H_f^-1)_ee, sigma_n the markers' noise and H_f the frame's normal
matrix of pose and offsets. The sums over frames give sigma: the moments of the offsets less what the noise gives
them.
"""
from __future__ import annotations

import numpy as np

from .calibrate import _Problem


def slack_moments(parent, origin, marker_segment, marker_local, observed, rot, root_pos, children,
                  chunk: int = 128) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per joint of ``children`` (child segments), over the frames where both its segments show three markers or more:
    the sums of |e_f|^2 and of tr(H_f^-1)_ee (see the module), and how many frames. The skeleton (``parent``,
    ``origin``, ``marker_segment``, ``marker_local``) and the poses (``rot``, ``root_pos``) are a rigid fit's on the
    frames ``observed``; e_f is one Gauss-Newton step from there (the offsets enter about linearly)."""
    parent = np.asarray(parent)
    seg = np.asarray(marker_segment)
    children = [int(c) for c in children]
    ns = len(children)
    pr = _Problem(parent, seg, observed, children, np.zeros(ns))
    F = observed.shape[0]
    p = np.hstack([np.asarray(root_pos, dtype=float), np.zeros((F, 3 * ns))])
    d = pr.offsets(origin)
    l = np.asarray(marker_local, dtype=float)
    seen = np.isfinite(observed).all(-1)
    per = np.stack([seen[:, seg == s].sum(1) for s in range(len(parent))], 1)  # (F, S) markers seen
    ok = np.stack([(per[:, c] >= 3) & (per[:, parent[c]] >= 3) for c in children], 1).astype(float)  # (F, ns)
    e2, tr = np.zeros(ns), np.zeros(ns)
    for a in range(0, F, chunk):
        sl = slice(a, min(F, a + chunk))
        Hff, X, _, _ = pr.normal_equations(sl, p, rot, d, l)
        # a segment a frame does not see leaves its rotation free: a tiny ridge, its rows apart from the rest
        Hse = np.linalg.inv(Hff + 1e-6 * np.eye(pr.nf))[:, pr.se]  # the offsets' rows of the inverse
        e = -(Hse @ X[..., -1:])[..., 0].reshape(-1, ns, 3)
        e2 += np.einsum("fci,fci,fc->c", e, e, ok[sl])
        tr += np.einsum("fci,fc->c", np.diagonal(Hse[:, :, pr.se], axis1=1, axis2=2).reshape(-1, ns, 3), ok[sl])
    return e2, tr, ok.sum(0)


def slack_sigma(parent, origin, marker_segment, marker_local, observed, rot, root_pos, children,
                noise: float) -> float:
    """One sigma (mm per axis) for the joints of ``children`` together, from :func:`slack_moments` and the markers'
    ``noise`` (mm per axis); 0 where the noise explains the offsets."""
    if not len(children):
        return 0.0
    e2, tr, n = slack_moments(parent, origin, marker_segment, marker_local, observed, rot, root_pos, children)
    if n.sum() == 0:
        return 0.0
    return float(np.sqrt(max(0.0, (e2.sum() - noise**2 * tr.sum()) / (3.0 * n.sum()))))
