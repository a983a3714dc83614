"""Batched skeleton inverse kinematics: segment rotations and root position per frame.

The skeleton is a tree of rigid segments. Segment ``s`` has a rest-pose origin
``origin[s]`` (a child's origin is its joint with the parent) and carries
markers at ``origin[s] + marker_local[m]`` at rest. At frame ``f`` every segment
has a *global* rotation ``R_s`` (rest pose -> pose at ``f``) and the root
segment's origin is at ``p``. Forward kinematics::

    P_root = p
    P_c    = P_parent + R_parent @ (origin[c] - origin[parent])
    x_m    = P_s + R_s @ marker_local[m]          (m on segment s)

:func:`solve_ik` minimises, for every frame independently but vectorised over
all frames,

    sum_m w_m |x_m - y_m|^2  +  prior_weight * sum_s |log(R_s R_prior,s^T)|^2

by Levenberg-Marquardt with global left-multiplicative increments
``R_s <- exp([d_s]x) R_s``. No Jacobian is formed: a segment's gradient and
Gauss-Newton Hessian come from a few per-frame sums over its markers
(weighted centroids and cross-covariances, computed once), and the damped
normal equations are solved by eliminating the segments leaves first, each
leaving a 3x3 stiffness on its joint for the parent (the articulated-body
recursion). An iteration is O(S) 3x3 operations per frame, whatever the
number of markers and the depth of the tree; so is the change of the cost
that decides whether a step is taken, computed from the same sums and the
increments themselves (exact to rounding of the change, not of the cost).
A frame leaves the iteration as soon as it has converged.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..allocator import keep_large_blocks
from ..parallel import run_blocks
from .problem import _Model, _Tree
from .planes import (
    _c_dot,
    _c_expm1,
    _c_is_rotation,
    _c_log,
    _c_mm,
    _c_mv,
    _planes,
    _project_so3,
    _unplanes,
)
from .start import _initial_rotations, _interp_fill, _root_from_rotations

__all__ = ["IKResult", "solve_ik"]

#: Frames solved together: large enough that numpy's per-call overhead is
#: small, small enough that the working arrays stay in the processor's cache.
_BLOCK = 2048


@dataclass(frozen=True, eq=False)
class IKResult:
    """The result of :func:`solve_ik`.

    root_pos : (F, 3) ndarray
        Root segment origin per frame (mm).
    rot : (F, S, 3, 3) ndarray
        Global segment rotations relative to the rest pose.
    residual : (F, M) ndarray
        Distance of each marker from its model position after the fit (mm);
        NaN where the marker is not seen or belongs to no segment.
    n_iter : int
        Number of iterations run (at most ``iterations``; the most any frame needed).
    converged : (F,) ndarray of bool
        Whether the frame converged: its last step was below the tolerance,
        or the linearised model could no longer lower its cost.
    """

    root_pos: np.ndarray
    rot: np.ndarray
    residual: np.ndarray
    n_iter: int
    converged: np.ndarray


# --------------------------------------------------------------------------- solver


def solve_ik(
    parent: np.ndarray,
    origin: np.ndarray,
    marker_segment: np.ndarray,
    marker_local: np.ndarray,
    observed: np.ndarray,
    *,
    init_rot: np.ndarray | None = None,
    init_root: np.ndarray | None = None,
    prior_rot: np.ndarray | None = None,
    weights: np.ndarray | None = None,
    iterations: int = 10,
    damping: float = 1e-3,
    prior_weight: float = 100.0,
    tol: float = 1e-6,
    out: np.ndarray | None = None,
) -> IKResult:
    """Segment rotations and root position that best fit the markers, every frame.

    Minimises, per frame (all frames at once, no loop over frames),
    ``sum_m w_m |x_m - y_m|^2 + prior_weight * sum_s |log(R_s R_prior,s^T)|^2``
    where ``x_m`` is the forward-kinematics position of marker ``m`` (see the
    module docstring), by Levenberg-Marquardt with a damping adapted per frame.

    Parameters
    ----------
    parent : (S,) int ndarray
        Parent of every segment, -1 for the (single) root. Any order; it is
        sorted topologically inside.
    origin : (S, 3) ndarray
        Rest-pose segment origins (mm); a child's origin is its joint with the parent.
    marker_segment : (M,) int ndarray
        Segment carrying each marker, -1 for markers to ignore.
    marker_local : (M, 3) ndarray
        Marker rest position minus its segment's origin (mm).
    observed : (F, M, 3) ndarray
        Observed markers (mm), NaN where not seen.
    init_rot : (F, S, 3, 3) ndarray, optional
        Starting rotations (projected onto rotations). Default: ``prior_rot``.
    init_root : (F, 3) ndarray, optional
        Starting root positions. Default: from the starting rotations, the
        weighted mean offset of the observed markers from the model; frames
        without markers are interpolated linearly over time.
    prior_rot : (F, S, 3, 3) ndarray, optional
        Target of the rotation prior. Default: built from the data — per
        segment, Kabsch of its markers where at least 3 are seen and spread
        across their main axis by at least 5% of their extent along it;
        else Kabsch of its markers plus the joints placed by the neighbouring
        segments solved in that frame; else its rotation relative to its
        parent slerped over time between such frames (held at the ends) or,
        for a segment never solved, its parent's rotation; finally, where
        the available points give a single direction, the smallest rotation
        of that guess matching it. So the
        prior agrees with the data where the data determine the rotation,
        and fills gaps and undetermined twists smoothly. Where it is only
        a guess (gaps, chains of poorly marked segments) it pulls the
        solution slightly away from the data's optimum: about
        ``prior_weight * angle / stiffness`` rad.
    weights : (F, M) or (M,) ndarray, optional
        Non-negative marker weights (default 1; NaN markers get 0).
    iterations : int, optional
        Maximum number of Levenberg-Marquardt iterations.
    damping : float, optional
        Initial Levenberg-Marquardt damping: every segment's rotation block
        and the root block are scaled by ``1 + damping``; adapted per frame
        from the gain ratio (Nielsen).
    prior_weight : float, optional
        Weight of the rotation prior in mm^2 per rad^2: the prior pulls like
        one marker ``sqrt(prior_weight)`` mm from the rotation axis (default:
        10 mm; a marker 100 mm from its joint weighs 10^4). Keep it positive
        so that segments with too few markers (or none) in a frame stay
        determined.
    tol : float, optional
        A frame has converged (and leaves the iteration) when its pose is
        estimated to be within ``tol`` mm of the solution, or when the
        linearised model can no longer lower its cost. A step's size is how
        far it moves what the skeleton carries: the largest, over segments, of
        its origin's change plus its rotation's change times its reach (the
        farthest of its markers and children's joints from its origin; the
        skeleton's extent for a segment that carries neither); the distance left is estimated as
        the next step's size: the last step times the ratio of the last two
        (Gauss-Newton converges linearly, fast here), or after a first or
        rejected step the step itself. With a motion-capture start (a few
        degrees off), ``0.1`` stops most frames after 2 iterations, the rest
        after 3, with joints within a few hundredths of a millimetre of the
        fully converged solution.
    out : (F, S, 3, 3) ndarray, optional
        Where to write the rotations (returned as ``rot``). It may be
        ``prior_rot`` or ``init_rot`` itself: frames are read before they are
        overwritten. Saves allocating (and the system mapping in) a large array.

    Returns
    -------
    IKResult
        ``root_pos`` (F, 3), ``rot`` (F, S, 3, 3) in the caller's segment
        order, ``residual`` (F, M), ``n_iter``, ``converged`` (F,). Pose
        arrays are finite in every frame, including frames where nothing is
        seen (held or interpolated); ``residual`` is NaN for unseen markers.

    Raises
    ------
    ValueError
        Inconsistent shapes, a parent array that is not a tree, or no marker
        on any segment seen in any frame.
    """
    parent = np.asarray(parent).astype(int)
    origin = np.asarray(origin, dtype=float)
    marker_segment = np.asarray(marker_segment).astype(int)
    marker_local = np.asarray(marker_local, dtype=float)
    observed = np.asarray(observed, dtype=float)
    S = len(parent)
    if parent.ndim != 1 or S == 0:
        raise ValueError("parent must be a non-empty 1-d array")
    if origin.shape != (S, 3):
        raise ValueError(f"origin must be ({S}, 3), got {origin.shape}")
    M = len(marker_segment)
    if marker_local.shape != (M, 3):
        raise ValueError(f"marker_local must be ({M}, 3), got {marker_local.shape}")
    if observed.ndim != 3 or observed.shape[1:] != (M, 3):
        raise ValueError(f"observed must be (F, {M}, 3), got {observed.shape}")
    if np.any(marker_segment < -1) or np.any(marker_segment >= S):
        raise ValueError("marker_segment must be -1 or a segment index")
    if not (np.isfinite(origin).all() and np.isfinite(marker_local[marker_segment >= 0]).all()):
        raise ValueError("origin and marker_local must be finite")
    F = observed.shape[0]
    tree = _Tree(parent)
    inv = np.empty(S, dtype=int)
    inv[tree.perm] = np.arange(S)

    used = np.flatnonzero(marker_segment >= 0)
    seg = inv[marker_segment[used]]
    model = _Model(tree, origin[tree.perm], seg, marker_local[used])
    # which markers are seen: finite coordinates (a NaN or inf in any of them makes the sum non-finite)
    seen = np.isfinite(observed[:, :, 0] + observed[:, :, 1] + observed[:, :, 2])[:, used]
    if weights is None:
        w_all = None
        any_seen = F > 0 and bool(seen.any())
    else:
        w_all = np.broadcast_to(np.asarray(weights, dtype=float), (F, M))[:, used]
        if not np.all(np.isfinite(w_all)) or np.any(w_all < 0):
            raise ValueError("weights must be finite and non-negative")
        any_seen = F > 0 and bool(np.any(seen & (w_all > 0)))
    if not any_seen:
        raise ValueError("no marker on any segment is seen in any frame: nothing to solve")

    def data(lo: int, hi: int) -> tuple[np.ndarray, np.ndarray]:
        """Observations (0 where unseen) and weights (0 where unseen) of frames lo:hi, in slots."""
        yb = observed[lo:hi][:, used]
        sb = seen[lo:hi]
        yb[~sb] = 0.0
        wb = sb.astype(float) if w_all is None else np.where(sb, w_all[lo:hi], 0.0)
        return model.planes(yb, wb)

    pw = float(prior_weight)
    if pw < 0 or damping < 0:
        raise ValueError("prior_weight and damping must be non-negative")

    # prior and starting point: per block, in the tree's order, as component planes
    if prior_rot is None:
        yt = np.where(seen[..., None], observed[:, used], 0.0)
        wt = seen.astype(float) if w_all is None else np.where(seen, w_all, 0.0)
        R_prior, prior_perm = _initial_rotations(model, yt, wt), None
        del yt, wt
    else:
        R_prior, prior_perm = np.asarray(prior_rot, dtype=float), tree.perm
        if R_prior.shape != (F, S, 3, 3) or not np.isfinite(R_prior).all():
            raise ValueError(f"prior_rot must be finite, ({F}, {S}, 3, 3)")
    if init_rot is not None:
        init_rot = np.asarray(init_rot, dtype=float)
        if init_rot.shape != (F, S, 3, 3) or not np.isfinite(init_rot).all():
            raise ValueError(f"init_rot must be finite, ({F}, {S}, 3, 3)")
    start, start_perm = (R_prior, prior_perm) if init_rot is None else (init_rot, tree.perm)
    keep_large_blocks()
    blocks = [(lo, min(lo + _BLOCK, F)) for lo in range(0, F, _BLOCK)]
    if init_root is None:
        p0 = np.empty((F, 3))
        has = np.empty(F, dtype=bool)
        for lo, hi in blocks:
            st = model.stats(*data(lo, hi))
            pb, has[lo:hi] = _root_from_rotations(model, _rotation_planes(start, start_perm, lo, hi), st)
            p0[lo:hi] = pb.T
        p0 = _interp_fill(p0, has)
    else:
        p0 = np.array(init_root, dtype=float)
        if p0.shape != (F, 3) or not np.isfinite(p0).all():
            raise ValueError(f"init_root must be finite, ({F}, 3)")

    # length scale: the skeleton's extent (the reach of a segment that carries nothing; the 3x3 blocks' floor)
    pts = np.concatenate([model.origin, model.origin[seg] + model.local])
    scale = max(float(np.linalg.norm(pts - model.origin[0], axis=1).max()), 1.0)
    floor = 1e-12 * scale**2  # keeps every 3x3 block invertible
    reach = model.reach(scale)  # the convergence test's lever of each segment's turn

    if out is None:
        rot = np.empty((F, S, 3, 3))
    elif out.shape != (F, S, 3, 3) or out.dtype != np.float64:
        raise ValueError(f"out must be a float64 ({F}, {S}, 3, 3) array")
    else:
        rot = out
    root_pos = np.empty((F, 3))
    res = np.full((F, M), np.nan)
    converged = np.zeros(F, dtype=bool)

    def solve_block(block: tuple[int, int]) -> int:
        """Solve frames lo:hi (blocks are independent: each reads and writes its own frames only)."""
        lo, hi = block
        yk, wk = data(lo, hi)
        st = model.stats(yk, wk)
        Rp = _rotation_planes(R_prior, prior_perm, lo, hi)
        R = Rp if init_rot is None else _rotation_planes(init_rot, tree.perm, lo, hi)
        p = np.ascontiguousarray(p0[lo:hi].T)
        R, p, converged[lo:hi], it = _iterate(model, R, p, st, Rp, pw, int(iterations), damping, tol, floor, reach)
        r = model.markers(p, R) - yk
        dist = model.unpack(np.sqrt(np.einsum("kisf,kisf->ksf", r, r)))
        res[lo:hi, used] = np.where(seen[lo:hi], dist, np.nan)
        Rs = _unplanes(R)  # (S, n, 3, 3) view
        for j in range(S):  # one strided copy per segment (faster than a gather and a transpose)
            rot[lo:hi, j] = Rs[inv[j]]
        root_pos[lo:hi] = p.T
        return it

    n_iter = max(run_blocks(solve_block, blocks), default=0)
    return IKResult(root_pos=root_pos, rot=rot, residual=res, n_iter=n_iter, converged=converged)


def _rotation_planes(R: np.ndarray, perm: np.ndarray | None, lo: int, hi: int) -> np.ndarray:
    """Frames lo:hi of rotations (F, S, 3, 3), segments reordered by ``perm``, as planes
    (3, 3, S, n), projected onto rotations where they are not rotations to 1e-9."""
    Rt = R[lo:hi].transpose(2, 3, 1, 0)
    Rc = np.ascontiguousarray(Rt) if perm is None else np.take(Rt, perm, axis=2)
    if _c_is_rotation(Rc):
        return Rc
    return np.ascontiguousarray(_planes(_project_so3(_unplanes(Rc))))


def _iterate(
    model: _Model,
    R: np.ndarray,
    p: np.ndarray,
    st: dict[str, np.ndarray],
    R_prior: np.ndarray,
    pw: float,
    iterations: int,
    damping: float,
    tol: float,
    floor: float,
    reach: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Levenberg-Marquardt on one block of frames: (R, p, converged, iterations run).

    ``R`` (3, 3, S, n) and ``p`` (3, n) the start, ``st`` the data's sums,
    ``R_prior`` (3, 3, S, n). A frame leaves as soon as it has converged:
    its pose is kept and every array is cut down to the frames still
    iterating. The change of the cost is computed from the change of the pose
    itself (``R' - R = (exp([d]x) - I) R`` and the bones and origins it moves),
    so that its rounding is that of the change, not of the cost.
    """
    n = p.shape[-1]
    RpT = np.ascontiguousarray(R_prior.transpose(1, 0, 2, 3))
    W, lbar, ybar, Cc = st["W"], st["lbar"], st["ybar"], st["Cc"]
    G, P = model.fk(p, R)
    a = _c_mv(R, lbar)
    d = P + a - ybar
    e = np.zeros(a.shape) if R is R_prior else _c_log(_c_mm(R, RpT))
    cost = (st["c0"] + W * _c_dot(d, d) - 2 * np.einsum("ijsf,ijsf->sf", R, Cc) + pw * _c_dot(e, e)).sum(0)
    st = {k: v for k, v in st.items() if k != "c0"}
    lam = np.full(n, float(damping))
    nu = np.full(n, 2.0)
    R_out = np.empty_like(R)
    p_out = np.empty_like(p)
    conv = np.zeros(n, dtype=bool)
    idx = np.arange(n)  # the frames still iterating
    n_iter = 0
    last = np.full(n, np.inf)  # the last step, if it was taken
    for _ in range(iterations):
        n_iter += 1
        gP0, gd0, A = model.gradient(R, a, d, st)
        fac = model.factor(R, G, A, st, pw, lam, floor)
        gd = gd0 + pw * e
        xP, xd, q = model.solve(fac, gP0, gd)
        dp, dr = -xP[:, 0], -xd
        dR = _c_mm(_c_expm1(dr), R)
        dG = model.bones(dR)
        dP = model.chain(dp, dG)
        da = _c_mv(dR, lbar)
        dd = da + dP
        R2 = R + dR
        e2 = _c_log(_c_mm(R2, RpT))
        # cost change: data W |d|^2 - 2 <R, Cc> (+ constants) and prior pw |e|^2
        dc = (W * _c_dot(dd, 2 * d + dd) - 2 * np.einsum("ijsf,ijsf->sf", dR, Cc) + pw * _c_dot(e2 - e, e2 + e)).sum(0)
        eps = 1e-12 * np.maximum(cost, 0.0) + 1e-18  # the rounding level of the cost
        ok = dc <= eps
        # how far the step moves what the skeleton carries: every segment's origin, plus its turn times its reach
        step = (np.sqrt(_c_dot(dP, dP)) + reach[:, None] * np.sqrt(_c_dot(dr, dr))).max(0)
        # the distance left to the solution: about the next step, i.e. this one times the rate
        # at which the (accepted) steps shrink; without a rate, the step itself
        left = np.where(ok & (last < np.inf), step * np.minimum(1.0, step / np.maximum(last, 1e-300)), step)
        last = np.where(ok, step, np.inf)
        pred = model.predicted(xP, xd, q, gP0, gd, lam, floor)
        # Nielsen's damping update from the gain ratio (actual / predicted decrease)
        rho = np.where(pred <= eps, 1.0, -dc / np.maximum(pred, 1e-300))  # rounding level: trust the model
        lam = np.where(ok, np.maximum(lam * np.maximum(1 / 3, 1 - (2 * np.minimum(rho, 1) - 1) ** 3), 1e-12), lam * nu)
        nu = np.where(ok, 2.0, nu * 2)
        # converged: the step is below tol, or the linear model can no longer lower the cost
        done = (left <= tol) | (ok & (pred <= eps))
        if not ok.all():  # rejected steps: nothing moves
            bad = ~ok
            for x in (dp, dG, dP, da, dd):
                x[..., bad] = 0.0
            dc[bad] = 0.0
            R2[..., bad] = R[..., bad]
            e2[..., bad] = e[..., bad]
        p = p + dp
        R, e = R2, e2
        G += dG
        P += dP
        a += da
        d += dd
        cost += dc
        if done.any():
            R_out[..., idx[done]] = R[..., done]
            p_out[:, idx[done]] = p[:, done]
            conv[idx[done]] = True
            keep = np.flatnonzero(~done)
            idx = idx[keep]
            if not idx.size:
                break
            p, R, G, P, a, d, e, RpT, cost, lam, nu, last = (
                np.take(x, keep, axis=-1) for x in (p, R, G, P, a, d, e, RpT, cost, lam, nu, last)
            )
            st = {k: np.take(v, keep, axis=-1) for k, v in st.items()}
            W, lbar, ybar, Cc = st["W"], st["lbar"], st["ybar"], st["Cc"]
    if idx.size:
        R_out[..., idx] = R
        p_out[:, idx] = p
    return R_out, p_out, conv, n_iter
