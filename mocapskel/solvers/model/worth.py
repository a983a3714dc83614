"""What a take's frames are worth to the joints: the spread of the joints' estimates that the residuals show, against
what the model's independent noise gives (the sandwich), measured at a fit with rigid joints."""
from __future__ import annotations

import numpy as np

from .joint_map import NOISE_FLOOR_MM
from .effective import frames_per_independent
from .uncertainty import _fitted, _gauged, _joint_operators, _pose_factors, _scores, segment_sizes

__all__ = ["joint_overdispersion"]


def joint_overdispersion(skel, prior_scale: float = 1.0) -> float:
    """How many times the variance of the joints' estimates that the residuals show exceeds what the model's
    independent noise gives, over every joint (at least 1): the sum over the joints of the trace of the sandwich
    covariance ``B^-1 S B^-1`` over that of ``B^-1``, each joint's position taken against its frame's markers
    (:func:`joint_uncertainty`'s). ``B`` is the posterior precision over the constant unknowns with every pose
    eliminated, under a weak prior of ``prior_scale`` times the child's size that only keeps it invertible; ``S``
    the spread of the frames' scores about their mean, the Bartlett-weighted sum of their products over lags up to
    one independent observation's length (:func:`frames_per_independent`; Newey and West 1987). ``skel``: a fit
    with rigid joints (soft joints' offsets take up the very misfit this measures).

    Skin that slides with the pose gives scores that stay alike from frame to frame and pull the same way: their
    sum spreads more than independent noise lets it. At the model path's MAP with rigid joints: the generated
    48-marker range of motion (soft tissue independent of the pose) 1.1, the realistic generator's walks 1.2-2.0,
    real takes of people 6-13, 21 where one segment is a body that is not rigid (BENCHMARKS, "Why the generated
    takes and the real ones pull opposite ways"). It is the factor by which the frames, counted as independent,
    overstate what they say about the joints: the composite likelihood's magnitude adjustment (Pauli, Racugno and
    Ventura 2011). 1 where the residual is below :data:`~mocapskel.solvers.model.joint_map.NOISE_FLOOR_MM` (a
    noise-free take's is the solver's tolerance)."""
    if skel.pose_rot is None or skel.pose_frames is None or skel.joints is None:
        return 1.0
    ref = int(np.searchsorted(skel.pose_frames, skel.rest_frame))
    if not (ref < skel.pose_frames.size and skel.pose_frames[ref] == skel.rest_frame):
        return 1.0
    pts = skel.joints.topology.segments.markers.points[skel.pose_frames]
    fit = _fitted(skel.parent, skel.origin, skel.marker_segment, skel.marker_local, pts, skel.pose_rot,
                  skel.pose_root, ref)
    if fit is None:
        return 1.0
    pr, d, l, R, p, _, s2, fix_g, H0 = fit
    if s2 < NOISE_FLOOR_MM**2:  # below what an optical system resolves the residual is the solver's, not the take's
        return 1.0
    kids = np.array(pr.kids, dtype=int)
    size = segment_sizes(skel.parent, skel.origin, skel.marker_segment, skel.marker_local)
    prior_sd = np.repeat(np.maximum(prior_scale * size[kids], 1.0), 3)
    A = _joint_operators(pr, l, d, kids)[0]
    P = (A.T / prior_sd**2) @ A
    Z = np.linalg.solve(_gauged(H0 / s2 + P, fix_g)[0], A.T)  # (ng, 3K)
    sc = _scores(pr, R, _pose_factors(pr, p, R, d, l, ref), Z, fix_g) / s2
    sc = sc - sc.mean(0)  # their spread about their mean (which the prior's pull sets at the MAP)
    lags = int(round(frames_per_independent(skel)))
    spread = sc.T @ sc
    for k in range(1, min(lags, sc.shape[0] - 1) + 1):
        g = sc[k:].T @ sc[:-k]
        spread += (1.0 - k / (lags + 1.0)) * (g + g.T)
    model = float(np.trace(A @ Z))
    sand = float(np.trace(spread + Z.T @ P @ Z))
    return max(1.0, sand / model) if model > 0 else 1.0
