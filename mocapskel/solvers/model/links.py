"""Two joints with a link of no markers between them, in place of one joint.

A robot arm or a rig may carry no marker on a link: its two neighbours then move as if joined by two joints a
fixed distance apart, not by one point. One joint there cannot fit: the model's misfit follows the joint angles and
pulls the joint far along any line the markers leave free (the joints stage's "free along a line"). The model of a
take then gets one more segment, with no markers, between the two: its joint with the parent is a point ``a`` fixed
in the parent, its child's joint a point ``b`` fixed in the child, and the link keeps them ``L`` apart. In the
parent's frame ``b`` moves on a sphere of radius ``L`` about ``a`` (:func:`fit_link`, a sphere fit on the child's
motion relative to the parent); the model's own score then chooses between the two models (:func:`with_links`).
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ...artifacts import Skeleton
from ..ik.motion import _centres_by_edges, _edges, segment_shapes
from ..ik.segment_poses import segment_poses


@dataclass(frozen=True)
class Link:
    """child : the segment that hangs on the link; a : (3,) the link's joint with the parent, in the parent's
    rest axes from its origin; b : (3,) its joint with the child, in the child's rest axes from its origin;
    length : |a - b| (mm); rms : the fit's rms distance off the sphere (mm); ball_rms : the rms distance of the one
    joint's place in the child from its mean place in the parent (the one-joint model's misfit, mm)."""

    child: int
    a: np.ndarray
    b: np.ndarray
    length: float
    rms: float
    ball_rms: float


def fit_link(Rr: np.ndarray, tr: np.ndarray, b0: np.ndarray, ridge: float = 1e-3,
             shortest: float = 1e-2) -> tuple[np.ndarray, np.ndarray, float, float]:
    """The points ``a`` (parent) and ``b`` (child) of a link: ``b``'s path ``Rr b + tr`` (the child's pose in the
    parent's frame, (F, 3, 3) and (F, 3)) as near as it gets to a sphere about ``a``. Least squares of the distances
    off the sphere from ``b0`` (``a`` at the start's mean place). Along what the motion leaves free the link is as
    short as the data allow (``shortest`` x its length, a hundredth of a millimetre per millimetre: between two
    parallel axes, their common normal, the link length of Denavit and Hartenberg), and ``a`` and ``b`` stay near
    the start (a ``ridge`` ten times weaker: the common normal slides along the axes). Returns (a, b, L, rms off the
    sphere)."""
    from scipy.optimize import least_squares  # here: importing it costs a third of a second, and few fits need it

    ok = np.isfinite(Rr[:, 0, 0]) & np.isfinite(tr).all(1)
    Rr, tr = Rr[ok], tr[ok]
    x0 = Rr @ b0 + tr
    a0 = x0.mean(0)
    L0 = float(np.mean(np.linalg.norm(x0 - a0, axis=1)))

    def res(z):
        a, b, L = z[:3], z[3:6], z[6]
        d = np.linalg.norm(Rr @ b + tr - a, axis=1)
        return np.concatenate([d - L, ridge * (a - a0), ridge * (b - b0), [shortest * L]])

    def jac(z):
        a, b = z[:3], z[3:6]
        v = Rr @ b + tr - a
        u = v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)
        J = np.zeros((len(u) + 7, 7))
        J[: len(u), :3] = -u
        J[: len(u), 3:6] = np.einsum("fi,fij->fj", u, Rr)
        J[: len(u), 6] = -1.0
        J[len(u) : len(u) + 6, :6] = ridge * np.eye(6)
        J[-1, 6] = shortest
        return J

    z = least_squares(res, np.concatenate([a0, b0, [L0]]), jac=jac, method="lm", xtol=1e-10, ftol=1e-12).x
    a, b, L = z[:3], z[3:6], abs(float(z[6]))
    rms = float(np.sqrt(np.mean((np.linalg.norm(Rr @ b + tr - a, axis=1) - L) ** 2)))
    return a, b, L, rms


def cut_poses(skel: Skeleton, points: np.ndarray, centres: np.ndarray, child: int) -> tuple[np.ndarray, np.ndarray]:
    """Each frame's pose of ``child``'s parent and of ``child`` from their own markers and their other joints'
    centres (``centres`` (F, K, 3) in ``_edges(skel)`` order), not from the joint between them: (R (F, 2, 3, 3),
    t (F, 2, 3)) with a rest point ``v`` (lab axes at the rest frame) at ``R v + t``; NaN where a pose is not fixed
    (fewer than three points, or in a line)."""
    cen = centres.copy()
    cen[:, np.flatnonzero(_edges(skel)[:, 1] == child)] = np.nan
    shapes, columns = segment_shapes(skel, (int(skel.parent[child]), child), points.shape[1], True)
    return segment_poses(shapes, columns, [points, cen], collinear_tol=1e-3)


def link_of(skel: Skeleton, points: np.ndarray, centres: np.ndarray, child: int) -> Link | None:
    """The link that best explains ``child``'s motion relative to its parent on the frames ``points`` (F, M, 3), both
    posed by :func:`cut_poses` (``centres``: the other joints' centres on those frames, ``_edges(skel)`` order):
    :func:`fit_link` from the one joint's place (the child's origin) and from the child's markers' centroid, the better
    kept. None where the two are posed together in fewer than ten frames."""
    p = int(skel.parent[child])
    R, t = cut_poses(skel, points, centres, child)
    ok = np.isfinite(R[:, :, 0, 0]).all(1)
    if ok.sum() < 10:
        return None
    R, t = R[ok], t[ok]
    Rr = np.einsum("fji,fjk->fik", R[:, 0], R[:, 1])
    tr = np.einsum("fji,fj->fi", R[:, 0], t[:, 1] - t[:, 0])
    j = skel.origin[child]
    path = Rr @ j + tr
    ball_rms = float(np.sqrt(np.mean(np.sum((path - path.mean(0)) ** 2, axis=1))))
    best = None
    mids = np.flatnonzero(skel.marker_segment == child)
    for b0 in [j] + ([j + skel.marker_local[mids].mean(0)] if mids.size else []):
        got = fit_link(Rr, tr, b0)
        if best is None or got[3] < best[3]:
            best = got
    a, b, L, rms = best
    return Link(child=child, a=a - skel.origin[p], b=b - j, length=L, rms=rms, ball_rms=ball_rms)


def with_link(skel: Skeleton, link: Link, name: str | None = None) -> Skeleton:
    """``skel`` with a segment of no markers (appended last) between ``link.child`` and its parent: its origin at
    ``link.a`` in the parent, the child's origin moved to ``link.b`` (its markers' and end site's offsets with it).
    The rest pose is the rest frame's, every rotation there the identity, so that rest axes are the lab's; the poses
    are dropped (IK poses the new tree)."""
    c = link.child
    p = int(skel.parent[c])
    S = len(skel.names)
    if name is None:  # the next free segment name (names can have gaps where segments were left out)
        name = next(f"seg{k:02d}" for k in range(S, S + len(skel.names) + 1) if f"seg{k:02d}" not in skel.names)
    origin = np.vstack([skel.origin, skel.origin[p] + link.a])
    origin[c] = skel.origin[c] + link.b
    parent = np.append(skel.parent, p)
    parent[c] = S
    local = skel.marker_local.copy()
    local[skel.marker_segment == c] -= link.b
    end = np.vstack([skel.end_site, np.zeros(3)])
    if not (skel.parent == c).any():
        end[c] = skel.end_site[c] - link.b
    info = dict(skel.info)
    info["links"] = list(info.get("links", [])) + [{
        "segment": name, "parent": skel.names[p], "child": skel.names[c],
        "length_mm": round(link.length, 1), "sphere_rms_mm": round(link.rms, 2), "one_joint_rms_mm": round(link.ball_rms, 1)}]
    return replace(skel, names=tuple(skel.names) + (name,), parent=parent, origin=origin,
                   marker_local=local, end_site=end, bone_length=np.append(skel.bone_length, 0.0),
                   noise=np.append(skel.noise, 0.0), info=info, pose_frames=None, pose_rot=None, pose_root=None)


def with_links(joints, starts: list, model: dict, frames: int) -> list:
    """``starts`` [(centres, skeleton)] with a link of no markers in place of each joint the joints stage held where it
    ran off along a line (one joint cannot fit there), where the model says so: the first start's MAP
    (:func:`~mocapskel.solvers.model.joint_map.map_refine` with ``model``'s keywords, on the refinement's ``frames``)
    scores lower with the link by more than the Bayesian information criterion charges for it (two turns a frame and
    the link's length). Each link is tried on top of those kept; the other starts get the same links, each fitted to
    its own poses."""
    from .joint_map import map_refine
    from .refinement import refinement_frames

    per = joints.info.get("per_joint") or []
    skel = starts[0][1]
    cands = []
    for e, (a, b) in enumerate(joints.topology.edges):
        if e < len(per) and "held_mm" in per[e]:
            cands.append(int(b) if skel.parent[int(b)] == int(a) else int(a))
    if not cands:
        return starts
    pts = joints.topology.segments.markers.points
    use = refinement_frames(skel, frames)
    if use.size < 10:
        return starts
    n_obs = 3 * int(np.isfinite(pts[use][:, skel.marker_segment >= 0]).all(-1).sum())
    charge = 0.5 * (2 * use.size + 1) * np.log(max(n_obs, 2))

    def score(sk: Skeleton) -> float:
        return map_refine(sk, starts[0][0], **model).info.get("refined", {}).get("neg_log_posterior", np.inf)

    nlp = score(skel)
    kept = []
    for c in cands:
        link = link_of(skel, pts[use], _centres_by_edges(skel, starts[0][0])[use], c)
        if link is None:
            continue
        trial = with_link(skel, link)
        nlp_l = score(trial)
        if nlp_l + charge < nlp:
            skel, nlp = trial, nlp_l
            kept.append(c)
    if not kept:
        return starts
    out = [(starts[0][0], skel)]
    for cen, sk in starts[1:]:
        for c in kept:
            link = link_of(sk, pts[use], _centres_by_edges(sk, cen)[use], c)
            if link is None:
                break
            sk = with_link(sk, link)
        else:
            out.append((cen, sk))
    return out
