"""Continuity of IK in time: solving again the short stretches where a segment
flips between equally good poses (unflip)."""
from __future__ import annotations

import numpy as np

from .solve import solve_ik


# --------------------------------------------------------------------------- continuity in time

#: Relative rounding level of a fit: poses whose marker rms differ by less than this times the skeleton's
#: size (its rest-pose markers' largest distance from their centroid) fit equally well.
ROUNDING = 1e-9
#: Weight (mm^2 per rad^2) of the prior that holds a pose solved again near itself while the markers polish it.
POLISH_PRIOR = 0.01


def _step_angles(R: np.ndarray) -> np.ndarray:
    """(F-1, ...) angle (deg) between consecutive rotations of (F, ..., 3, 3)."""
    c = (np.einsum("f...ij,f...ij->f...", R[1:], R[:-1]) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def _frame_rms(resid: np.ndarray) -> np.ndarray:
    """(F,) rms of the seen markers' residuals per frame (0 where none is seen)."""
    seen = np.isfinite(resid)
    n = seen.sum(1)
    return np.sqrt(np.where(seen, resid, 0.0).__pow__(2).sum(1) / np.maximum(n, 1))


def _worst_turn(steps: np.ndarray, F: int) -> np.ndarray:
    """(F,) the largest turn (over segments) of each frame from its previous or to its next frame."""
    w = steps.max(axis=1) if steps.size else np.zeros(max(F - 1, 0))
    out = np.zeros(F)
    out[1:] = w
    out[:-1] = np.maximum(out[:-1], w)
    return out


def unflip(
    parent: np.ndarray,
    origin: np.ndarray,
    marker_segment: np.ndarray,
    marker_local: np.ndarray,
    observed: np.ndarray,
    rot: np.ndarray,
    root_pos: np.ndarray,
    residual: np.ndarray,
    *,
    max_step_deg: float = 45.0,
    max_run: int = 60,
    rel_tol: float = 0.1,
    abs_tol_mm: float = 0.5,
    passes: int = 2,
    iterations: int = 10,
    prior_weight: float = 100.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """Make IK continuous in time where the markers allow more than one good pose.

    Where a segment's markers leave its rotation undetermined (one or two
    markers, or nearly collinear ones: the twist about their line is held only
    by the joints), per-frame IK can land on either of two equivalent
    solutions, or wander along the free twist, from one frame to the next: a
    joint turns by up to 180 degrees, or pops by hundreds of millimetres, while
    its markers move by a few. Here every stretch of at most ``max_run`` frames
    that a segment spends between two turns of more than ``max_step_deg`` in
    one frame is solved again, started from and held (``prior_weight``) by the
    segment's rotation slerped across it from the frames around it; a frame
    takes the new pose when its marker rms is no worse than ``(1 + rel_tol)``
    times the old one plus ``abs_tol_mm`` or the take's own level of fit (the
    median over frames of the marker rms, at least its rounding level),
    whichever is less: of two equally
    good solutions, the one near its neighbours. A stretch the markers really
    turn in keeps its poses (the new ones fit worse). The level caps the
    tolerance where the skeleton fits far better than half a millimetre: on a
    noise-free chain of links of 1 mm, a whole chain turned a third of its
    link length off its markers still "fitted as well" within 0.5 mm, and
    frames that turn fast (the refinement's spread frames) took such poses.
    Vectorised over frames: one solve per pass.

    Parameters
    ----------
    parent, origin, marker_segment, marker_local, observed
        As :func:`solve_ik`.
    rot : (F, S, 3, 3) ndarray
        Solved global rotations (changed in place and returned).
    root_pos : (F, 3) ndarray
    residual : (F, M) ndarray
    max_step_deg, max_run, rel_tol, abs_tol_mm, passes, iterations, prior_weight
        See above.

    Returns
    -------
    rot, root_pos, residual, info
        ``info``: ``{"steps_before": n, "steps_after": n, "frames_changed": n}``
        (segment-frames with a turn above ``max_step_deg``; frames given a new pose).
    """
    from ..rotations import slerp_fill

    F, S = rot.shape[:2]
    info = {"steps_before": 0, "steps_after": 0, "frames_changed": 0}
    if F < 3:
        return rot, root_pos, residual, info
    steps = _step_angles(rot)  # (F-1, S)
    info["steps_before"] = info["steps_after"] = int((steps > max_step_deg).sum())
    if not info["steps_before"]:
        return rot, root_pos, residual, info
    changed = np.zeros(F, dtype=bool)
    rms = _frame_rms(residual)
    seen_any = np.isfinite(residual).any(axis=1)
    level = float(np.median(rms[seen_any])) if seen_any.any() else 0.0
    used = np.asarray(marker_segment) >= 0
    # rounding: two poses the markers cannot tell apart fit to within a billionth of the skeleton's size
    rest = np.asarray(origin)[np.asarray(marker_segment)[used]] + np.asarray(marker_local)[used]
    size = float(np.linalg.norm(rest - rest.mean(axis=0), axis=1).max()) if rest.size else 0.0
    abs_tol = min(float(abs_tol_mm), max(level, ROUNDING * size))
    any_seen = np.isfinite(observed[:, used].sum(axis=2)).any(axis=1)  # frames IK can solve again
    for _ in range(passes):
        big = steps > max_step_deg
        bad = np.zeros((F, S), dtype=bool)
        for s in np.flatnonzero(big.any(axis=0)):
            rid = np.r_[0, np.cumsum(big[:, s])]  # stretch of every frame
            length = np.bincount(rid)
            bad[:, s] = length[rid] <= max_run
            if bad[:, s].all():  # nothing steady to hold it to
                bad[:, s] = False
        frames = np.flatnonzero(bad.any(axis=1) & any_seen)
        if not frames.size:
            break
        # the start and prior: every segment as solved, those in a short stretch slerped across it
        start = rot[frames]  # a copy
        for s in np.flatnonzero(bad.any(axis=0)):
            start[:, s] = slerp_fill(rot[:, s], ~bad[:, s])[frames]
        res = solve_ik(parent, origin, marker_segment, marker_local, observed[frames], init_rot=start,
                       init_root=root_pos[frames], prior_rot=start, iterations=iterations, prior_weight=prior_weight)
        del start
        # ...then, where the tolerance is the take's own level (it fits far better than half a millimetre),
        # let the markers decide what they fix: held by the slerp, the pose sits off their optimum by the
        # prior's pull (1e-3 mm on a noise-free leaf whose half turn is undone), which a fit of rounding level
        # would count as worse; held lightly by itself, it keeps the free twist the slerp gave it
        if abs_tol < abs_tol_mm:
            res = solve_ik(parent, origin, marker_segment, marker_local, observed[frames], init_rot=res.rot,
                           init_root=res.root_pos, prior_rot=res.rot.copy(), iterations=iterations,
                           prior_weight=POLISH_PRIOR)
        new_rms = _frame_rms(res.residual)
        ok = new_rms <= (1.0 + rel_tol) * rms[frames] + abs_tol
        # ...and where the frame's largest turn from or to its neighbours does not grow
        # (judged with every equally good frame taken)
        where = np.full(F, -1)
        where[frames[ok]] = np.flatnonzero(ok)

        def taken(f: np.ndarray) -> np.ndarray:  # rotations of frames f with the equally good ones taken
            k = where[f]
            return np.where((k >= 0)[:, None, None, None], res.rot[np.maximum(k, 0)], rot[f])

        worst_new = np.zeros(frames.size)
        mine = taken(frames)
        for nb in (frames - 1, frames + 1):
            inside = (nb >= 0) & (nb < F)
            turn = _step_angles(np.stack([mine[inside], taken(nb[inside])]))[0].max(axis=-1)
            worst_new[inside] = np.maximum(worst_new[inside], turn)
        del mine
        worst_old = _worst_turn(steps, F)[frames]
        ok &= worst_new <= np.maximum(worst_old, max_step_deg)
        if not ok.any():
            break
        f = frames[ok]
        rot[f], root_pos[f], residual[f], rms[f] = res.rot[ok], res.root_pos[ok], res.residual[ok], new_rms[ok]
        changed[f] = True
        steps = _step_angles(rot)
    info["steps_after"] = int((steps > max_step_deg).sum())
    info["frames_changed"] = int(changed.sum())
    return rot, root_pos, residual, info
