"""Each joint's uncertainty: the Laplace approximation of the skeleton model at a fitted skeleton.

The model (see :mod:`mocapskel.solvers.model.calibrate`): markers are points fixed on rigid segments
joined at fixed joint centres, plus isotropic Gaussian noise of one standard deviation ``sigma``
per coordinate. Its curvature at a fitted skeleton, on the refinement's frames, is the Gauss-Newton
matrix of the whole problem; the per-frame poses are eliminated by the Schur complement
(:meth:`~mocapskel.solvers.model.calibrate._Problem.eliminate`, vectorised over frames), which leaves
the reduced normal matrix over the constant unknowns (bone and marker offsets). Divided by
``sigma^2``, estimated from the same fit's residual with its degrees of freedom, and by how many of the
fit's frames one independent observation is worth (the residuals' correlation in time, measured from the
take: :func:`frames_per_independent`), it is the data's precision.

The curvature at the fitted poses counts as information what the noise alone put there: a hinge
turns about one axis, its fitted poses also turn a little about the others, fitted to the noise,
and those turns seem to place its centre along the axis (on a generated hinge, to about
``r / sqrt(F)`` for markers ``r`` from it over ``F`` frames, whatever the noise level: the
incidental-parameter bias of a profile over per-frame poses). That part is measured and taken
out: the poses are moved by the errors that noise of the take's level would give them (Gauss-Newton
steps for draws of that noise, in antithetic pairs), and the change this makes to the constant
unknowns' Jacobian, eliminated through the poses, is what the noise put in; its mean over the draws
is subtracted (the first step of SIMEX, Cook and Stefanski 1994) with ``NOISE_Z`` of its standard
deviations over, and what is left is clipped to positive semi-definite (relative to the posterior
precision, so that the clipping does not depend on the gauge). This is done along the directions the
prior touches (three per joint), where it can matter. A direction is then credited only with what
the data show beyond the noise.

Gauge: the reference frame's rotations are held (as the refinement holds them) and the root's origin
fixed by one of its joints; the quantity reported does not depend on it: each joint's position relative to
the best-fit frame of its child segment's markers (origin at their centroid, turned with them). A child of
one or two markers makes no such frame (two have no turn about their line: the joint's place about it is a
convention): its parent's markers serve when they make one, else the child's markers and its own children's
joints; else the child's, at the rest frame's turn (one marker: origin at it). Directions: the lab's axes at
the rest frame. Soft joints (the model path's, ``soft``): each frame's offsets are eliminated with its pose,
their Gaussian prior in the frame's block.

The residuals' own spread: the model's covariance takes the noise as independent and the model as
right. Where the residuals say otherwise (a marker sliding over its segment, a joint whose centre moves,
skin that follows the pose), the scores of the constant unknowns, per frame with that frame's pose
eliminated, spread more than the model's curvature says. Their spread over stretches of frames as long as
one independent observation (:func:`frames_per_independent`) gives the sandwich covariance ``B0^-1 (S + P)
B0^-1`` (Huber 1967; White 1982), ``B0`` the posterior precision with the frames as independent, ``P`` the
prior's; where it exceeds the model's own ``B0^-1`` the excess is added to each joint's covariance (where the
model holds it is about zero). Scores taken where a rule moved a joint off where the markers put it sum
to more than their spread: that also widens its region. Like the skin's part below, it is no part of the
model's information: the prior's share, and whether the prior sets a joint, come from the model alone.

The prior: an isotropic Gaussian on that position, centred where the fit put it, of sd ``prior_scale`` times
the child segment's size (the largest distance between two of its markers and joints at rest), in mm, the
data's precision in units of the take's own noise (more noise: the prior weighs more). Per joint: its sds
along the principal directions of the posterior covariance, and the prior's share of the precision along
each (``sd^2 / prior_sd^2``: 0 the data decide, 1 the prior); set by the prior where it exceeds ``SET_BY_PRIOR``.

What motion would fix it: a joint the markers cannot place along ``u`` turned (nearly) only about ``u``
(a hinge about its axis); a turn about the axis across both ``u`` and the child's bone places it.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from .calibrate import _exp, _hat, _hold_reference, _Problem
from .effective import frames_per_independent
from .skin import skin_motion
from ..parallel import run_blocks
from ..rotations import matrix_to_rotvec

__all__ = ["JointUncertainty", "joint_uncertainty", "segment_sizes", "PRIOR_SCALE", "SET_BY_PRIOR"]

#: Standard deviation of the prior on a joint's position, as a multiple of its child segment's size. The tightest
#: whose 95 % regions hold at least 80 % of the true errors on the realistic benchmark's tuning seeds with a margin
#: (0.15: 81 %, 0.2: 84 %; checking seeds 79 % and 83 %); 0.5 held about as many (87 %) in regions 1.6 times as wide.
PRIOR_SCALE = 0.2

#: The prior's share of the precision above which a direction is set by the prior, not the data.
SET_BY_PRIOR = 0.5

#: Antithetic pairs of noise draws that measure what the noise alone puts into the curvature.
NOISE_PAIRS = 3

#: That measure is removed with this many of its standard deviations over (the spread of the part the
#: noise put into this take's curvature, from how unevenly the frames share it, and of the draws' mean):
#: a direction is credited with what the data show beyond what noise alone would show there but
#: about once in a thousand. With two, one hinge in 24 (generated chains, 8 seeds) kept most of its
#: axis to the data (the prior's share 0.35).
NOISE_Z = 3.0

#: Directions (of unit posterior precision) where one pair of draws finds the noise's part under this
#: get no more draws: it changes their precision by about 1 % (their sd by half that).
SCREEN = 1e-2

#: Markers of a child segment closer to a line than this fraction of their spread (the second singular
#: value of their rotation basis over the first) give no turn about that line.
_LINE_RCOND = 1e-3


@dataclass(frozen=True, eq=False)
class JointUncertainty:
    """The uncertainty of every joint (arrays over the joints, by child segment ``kids``).

    kids : (K,) child segment of each joint.
    cov : (K, 3, 3) posterior covariance (mm^2) of the joint relative to the markers of ``frame``, lab axes at rest.
    spread : (K, 3, 3) what the residuals' own spread adds to it (the sandwich's excess: not in ``cov``, ``sd`` or
        ``prior_share``, no part of the model's information).
    sd : (K, 3) standard deviations (mm) along the principal directions of ``cov``, largest first.
    directions : (K, 3, 3) the principal directions (rows, unit), in the order of ``sd``.
    prior_share : (K, 3) the prior's share of the posterior precision along each direction.
    prior_sd : (K,) the prior's standard deviation (mm).
    frame : (K,) the segment whose markers the joint is measured against (:func:`_frame_segment`).
    frame_markers : (K,) points of that segment that define its frame (3 means three or more, not on a line).
    turned_about : (K, 3) the main axis of the joint's relative rotations (lab axes at rest), NaN if unknown.
    lacks_axis : (K, 3) the axis a turn about which would place the joint along ``directions[:, 0]``.
    noise_sd : the take's noise (mm per coordinate) from the fit's residual; dof its degrees of freedom.
    frames : frames of the fit. soft, pose_p : the soft joints (child segments) and (F, 3 + 3 ns) each frame's root
        origin and their offsets (:meth:`~mocapskel.solvers.model.calibrate._Problem.soft_offsets`).
    """

    kids: np.ndarray
    cov: np.ndarray
    spread: np.ndarray
    sd: np.ndarray
    directions: np.ndarray
    prior_share: np.ndarray
    prior_sd: np.ndarray
    frame: np.ndarray
    frame_markers: np.ndarray
    turned_about: np.ndarray
    lacks_axis: np.ndarray
    noise_sd: float
    dof: int
    frames: int
    soft: tuple = ()
    pose_p: np.ndarray | None = None

    @property
    def set_by_prior(self) -> np.ndarray:
        """(K,) whether the prior sets the joint along some direction."""
        return (self.prior_share > SET_BY_PRIOR).any(1)


def segment_sizes(parent: np.ndarray, origin: np.ndarray, marker_segment: np.ndarray,
                  marker_local: np.ndarray) -> np.ndarray:
    """(S,) each segment's size: the largest distance between two of its markers and joints at rest."""
    parent = np.asarray(parent)
    S = len(parent)
    seg = np.asarray(marker_segment)
    ok = (seg >= 0) & np.isfinite(marker_local).all(1)
    pos = np.full(marker_local.shape, np.nan)
    pos[ok] = origin[seg[ok]] + marker_local[ok]
    out = np.zeros(S)
    for s in range(S):
        pts = [pos[seg == s]]
        if parent[s] >= 0:
            pts.append(origin[s][None])
        pts.append(origin[np.flatnonzero(parent == s)])
        P = np.concatenate(pts)
        P = P[np.isfinite(P).all(1)]
        if len(P) > 1:
            out[s] = float(np.sqrt(((P[:, None] - P[None]) ** 2).sum(-1)).max())
    return out


def _frame_points(pr: _Problem, local: np.ndarray, s: int, bones: np.ndarray | None = None, skip: int = -1
                  ) -> tuple[np.ndarray, list[int]]:
    """Points that make segment ``s``'s frame: its markers (their offsets ``local``), and with ``bones``
    (S, 3) also its children's joints (their offsets from its origin) but child ``skip``'s; (positions (n, 3), each
    point's first column among the constant unknowns)."""
    ms = [int(m) for m in pr.used if pr.seg[m] == s]
    pos, cols = [local[m] for m in ms], [pr.gl[m] for m in ms]
    if bones is not None:
        for k in pr.kids:
            if int(pr.parent[k]) == s and k != skip:
                pos.append(bones[k])
                cols.append(pr.gi[k])
    return np.array(pos, dtype=float).reshape(-1, 3), cols


def _point_frame(pos: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """The best-fit frame of points at ``pos`` (n, 3) to first order: (their centroid, ``Bp`` (3, 3n): their
    moves to the frame's small turn, none about a line they lie on), and how many of them define that turn
    (0, 1, 2 or 3: three or more not on a line)."""
    n = len(pos)
    if not n:
        return np.zeros(3), np.zeros((3, 0)), 0
    cbar = pos.mean(0)
    # the points' small turn w moves point i by w x r_i = -hat(r_i) w
    B = -_hat(pos - cbar).reshape(-1, 3)
    sv = np.linalg.svd(B, compute_uv=False) if n > 1 else np.zeros(3)
    rank = int((sv > _LINE_RCOND * max(sv[0], 1e-300)).sum()) if n > 1 else 0
    Bp = np.linalg.pinv(B, rcond=_LINE_RCOND) if n > 1 else np.zeros((3, 3 * n))
    return cbar, Bp, (3 if rank >= 3 else n if n < 3 else 2)


def _frame_segment(pr: _Problem, local: np.ndarray, c: int, bones: np.ndarray) -> tuple[int, bool]:
    """What joint ``c`` is measured against: (segment, whether its children's joints join its markers).
    Its child's markers when they make a frame (three or more, not on a line); else its parent's when
    those do; else the child's markers and its own children's joints (a shank of two markers and its
    ankle), when those do; else the child's markers. Against a child of one or two markers the joint's
    turn about them is no quantity of the skeleton's (the segment's twist about its markers is a
    convention, and the joint's place about them with it), so that the data, which place the joint from
    the parent's side, would seem to leave it to the prior. A child of no markers (a link's) is measured
    against its parent's markers and other joints when its parent's markers alone make no frame."""
    if _point_frame(_frame_points(pr, local, c)[0])[2] == 3:
        return c, False
    p = int(pr.parent[c])
    if _point_frame(_frame_points(pr, local, p)[0])[2] == 3:
        return p, False
    if not len(_frame_points(pr, local, c)[0]) and _point_frame(_frame_points(pr, local, p, bones, c)[0])[2] == 3:
        return p, True  # a link of no markers (mocapskel.solvers.model.links): its parent's markers and other joints
    if _point_frame(_frame_points(pr, local, c, bones)[0])[2] == 3:
        return c, True
    return c, False


def _joint_operator(pr: _Problem, local: np.ndarray, c: int, s: int | None = None,
                    bones: np.ndarray | None = None, with_joints: bool = False) -> tuple[np.ndarray, int]:
    """(3, ng) first-order map from the constant unknowns to joint ``c``'s position relative to the
    best-fit frame of segment ``s``'s markers (its child ``c``, by default, or its parent; with
    ``with_joints``, the markers and its children's joints; ``bones`` (S, 3) every child's offset from its
    parent's origin; see the module docstring), and how many points define that frame's turn (0, 1, 2 or 3)."""
    s = c if s is None else int(s)
    pos, first = _frame_points(pr, local, s, bones if with_joints else None, skip=c)
    cbar, Bp, n = _point_frame(pos)
    A = np.zeros((3, pr.ng))
    if not len(pos):
        return A, 0
    # the joint sits at P in s's frame (the child's origin, 0; in the parent's, its bone offset d_c);
    # relative to the points' frame it moves by dP - t + hat(P - cbar) w, with t their mean move and
    # w = Bp (their moves)
    P = np.zeros(3)
    if s != c:
        P = np.asarray(bones[c], dtype=float)
        A[:, pr.gi[c] : pr.gi[c] + 3] = np.eye(3)
    T = np.tile(np.eye(3), (1, len(pos))) / len(pos)
    J = -T + _hat(P - cbar) @ Bp
    cols = np.concatenate([np.arange(f, f + 3) for f in first])
    A[:, cols] += J
    return A, n


def _joint_operators(pr: _Problem, l: np.ndarray, d: np.ndarray, kids: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(3K, ng) every joint of ``kids`` against its frame's markers (:func:`_joint_operator`, the frame
    :func:`_frame_segment`'s), stacked; (K,) each one's frame segment; (K,) how many points define that frame's turn."""
    frames = [_frame_segment(pr, l, int(c), d) for c in kids]
    ops = [_joint_operator(pr, l, int(c), f, d, j) for c, (f, j) in zip(kids, frames)]
    return (np.concatenate([a for a, _ in ops]), np.array([f for f, _ in frames], dtype=int),
            np.array([n for _, n in ops], dtype=int))


def _gauged(B: np.ndarray, fix_g: np.ndarray, scale: float | None = None) -> tuple[np.ndarray, float]:
    """A precision over the constant unknowns made invertible: the gauge's unknowns (no part of any joint's
    position) at ``scale`` (None: the largest diagonal entry), and a ridge of 1e-12 of it; and that scale."""
    if scale is None:
        scale = max(float(np.abs(np.diag(B)).max()), 1e-300)
    B = B.copy()
    B[fix_g, fix_g] = scale
    B += 1e-12 * scale * np.eye(B.shape[0])
    return B, scale


def _gauge_fixed(pr: _Problem) -> np.ndarray:
    """(ng,) which constant unknowns the gauge fixes: the root's origin, by one of its joints (or markers)."""
    fix_g = np.zeros(pr.ng, dtype=bool)
    rk0 = [c for c in pr.kids if pr.parent[c] == pr.root]
    if rk0:
        fix_g[pr.gi[rk0[0]] : pr.gi[rk0[0]] + 3] = True
    else:
        m0 = [int(m) for m in pr.used if pr.seg[m] == pr.root]
        if m0:
            fix_g[pr.gl[m0[0]] : pr.gl[m0[0]] + 3] = True
    return fix_g


def _damped(Hff: np.ndarray) -> np.ndarray:
    """Pose blocks with a relative ridge of 1e-10 on their diagonal, and 1 where it is zero: poses the
    markers do not fix (a segment unseen in a frame) meet no residual, so nothing of theirs reaches the
    constant unknowns. (A ridge in absolute units, relative to the largest entry, holds the root's position,
    whose entries are a thousandth of the rotations': the gauge's move of the root's origin then showed as
    information.)"""
    dg = np.diagonal(Hff, axis1=1, axis2=2)
    tiny = dg <= 1e-12 * np.maximum(dg.max(1, keepdims=True), 1e-300)
    out = Hff.copy()
    idx = np.arange(Hff.shape[1])
    out[:, idx, idx] += np.where(tiny, 1.0, 1e-10 * dg)
    return out


def _chunks(F: int, chunk: int) -> list[slice]:
    """An even number of equal stretches of at most ``chunk`` frames (two threads get equal shares)."""
    cut = np.linspace(0, F, 2 * -(-F // (2 * chunk)) + 1).round().astype(int)
    return [slice(int(a), int(b)) for a, b in zip(cut[:-1], cut[1:]) if b > a]


def reduced_normal_matrix(pr: _Problem, p, R, d, l, ref_frame: int, fix_g: np.ndarray, chunk: int = 128
                          ) -> np.ndarray:
    """The Gauss-Newton matrix over the constant unknowns with every pose eliminated (ng, ng), the
    reference frame's rotations held and the unknowns ``fix_g`` fixed (their rows and columns zero)."""
    ng = pr.ng

    def part(sl: slice) -> np.ndarray:
        Hff, X, Hgg_f, _ = pr.normal_equations(sl, p, R, d, l)
        _hold_reference(Hff, X, sl, ref_frame, pr.S)
        X[:, :, :ng][:, :, fix_g] = 0.0
        YtY, _ = pr.eliminate(_damped(Hff), X)
        return Hgg_f - YtY[:ng, :ng]

    H = np.zeros((ng, ng))
    for h in run_blocks(part, _chunks(p.shape[0], chunk)):  # summed in chunk order
        H += h
    H = 0.5 * (H + H.T)
    H[fix_g, :] = 0.0
    H[:, fix_g] = 0.0
    return H


def _g_columns(pr: _Problem, R: np.ndarray, w: np.ndarray, V: np.ndarray) -> np.ndarray:
    """(n, 3U, k) the weighted marker Jacobian of the constant unknowns times ``V`` (ng, k), at rotations
    ``R`` (n, S, 3, 3), its rows ordered as :meth:`~mocapskel.solvers.model.calibrate._Problem.jacobian`'s
    (coordinate, then marker): a bone offset moves every marker below its joint by its parent's rotation,
    a marker's offset its marker by its segment's rotation."""
    n, k, U, nd = R.shape[0], V.shape[1], pr.used.size, pr.nd
    Vd = V[:nd].reshape(-1, 3, k)
    Vl = V[nd:].reshape(U, 3, k)
    nk = Vd.shape[0]
    # one product per joint and per marker over all frames at once: (3n, 3) @ (3, k)
    Gd = (R[:, pr.kid_parent].transpose(1, 0, 2, 3).reshape(nk, 3 * n, 3) @ Vd).reshape(nk, n * 3 * k)
    Gl = R[:, pr.seg[pr.used]].transpose(1, 0, 2, 3).reshape(U, 3 * n, 3) @ Vl  # (U, 3n, k)
    G = (pr.sub @ Gd).reshape(U, n, 3, k) + Gl.reshape(U, n, 3, k)
    G *= w.T[:, :, None, None]
    return G.transpose(1, 2, 0, 3).reshape(n, 3 * U, k)


def _pose_factors(pr: _Problem, p, R, d, l, ref_frame: int, chunk: int = 128) -> list[tuple]:
    """Per chunk of frames: (its slice, the pose Jacobian transposed JfT (n, nf, 3U) with the reference
    frame's rotations held, ``Li`` (n, nf, nf) the inverse Cholesky factor of ``JfT JfT^T`` plus the soft joints'
    prior, the markers' weights (n, U), the residual (n, 3U, 1) in JfT's row order: coordinate, then marker)."""
    def one(sl: slice) -> tuple:
        JfT, _, _, r = pr.jacobian(sl, p, R, d, l)  # its rows zero where a marker is unseen
        if sl.start <= ref_frame < sl.stop:
            JfT[ref_frame - sl.start, 3 : 3 + 3 * pr.S] = 0.0
        D = JfT @ JfT.transpose(0, 2, 1)
        D[:, pr.se, pr.se] += pr.ws
        Li = np.linalg.inv(np.linalg.cholesky(_damped(D)))
        return sl, JfT, Li, pr.w[sl][:, pr.used], r.transpose(0, 2, 1).reshape(r.shape[0], -1, 1)

    return run_blocks(one, _chunks(p.shape[0], chunk))


def _noise_curvature(pr: _Problem, R: np.ndarray, factors: list[tuple], sigma: float, V: np.ndarray,
                     seed: tuple, pairs: int) -> tuple[np.ndarray, np.ndarray]:
    """What noise of level ``sigma`` puts into the reduced matrix along ``V`` (ng, k) through the poses,
    over ``pairs`` draws: for each, the pose errors ``delta = D^-1 Jf^T e`` that a draw ``e`` of that noise
    gives (the skeleton held), and the part of the constant unknowns' Jacobian that they change,
    ``G1 = (G(R + delta) - G(R - delta)) / 2`` (an antithetic pair: what is even in ``delta`` cancels),
    eliminated through the fitted poses: ``G1^T G1 - G1^T Jf D^-1 Jf^T G1``. Each stretch of frames draws
    from its own generator, seeded by ``seed`` and its index (the same draws on any number of threads).

    Returns its mean (k, k) and, per direction, the sum over frames of each frame's part squared,
    averaged over the draws (k,): how unevenly the frames share it (its spread, below)."""
    S = R.shape[1]
    k = V.shape[1]

    def one(j: int) -> tuple[np.ndarray, np.ndarray]:
        sl, JfT, Li, w, _ = factors[j]
        n = sl.stop - sl.start
        rng = np.random.default_rng((*seed, j))
        out, sq = np.zeros((k, k)), np.zeros(k)
        for _ in range(pairs):
            e = rng.normal(0.0, sigma, (n, JfT.shape[2], 1))
            step = (Li.transpose(0, 2, 1) @ (Li @ (JfT @ e)))[..., 0]  # D^-1 Jf^T e
            turn = _exp(step[:, 3 : 3 + 3 * S].reshape(n, S, 3))
            # G is linear in the rotations: G(R+) - G(R-) = G(R+ - R-)
            G1 = _g_columns(pr, 0.5 * (turn - np.swapaxes(turn, -1, -2)) @ R[sl], w, V)
            Y = Li @ (JfT @ G1)
            per_frame = (G1 * G1).sum(1) - (Y * Y).sum(1)  # (n, k)
            sq += (per_frame * per_frame).sum(0)
            G1, Y = G1.reshape(-1, k), Y.reshape(-1, k)
            out += G1.T @ G1 - Y.T @ Y
        return out, sq

    out, sq = np.zeros((k, k)), np.zeros(k)
    for o, q in run_blocks(one, range(len(factors))):  # summed in stretch order
        out += o
        sq += q
    return out / max(pairs, 1), sq / max(pairs, 1)


def _scores(pr: _Problem, R: np.ndarray, factors: list[tuple], Z: np.ndarray, fix_g: np.ndarray) -> np.ndarray:
    """(n, k) each frame's score of the constant unknowns, its pose eliminated, ``G^T (I - Jf D^-1 Jf^T) r``,
    times ``Z`` (ng, k) (the gauge's unknowns have no score)."""
    Zs = Z.copy()
    Zs[fix_g] = 0.0

    def one(j: int) -> np.ndarray:
        sl, JfT, Li, w, rr = factors[j]
        Gz = _g_columns(pr, R[sl], w, Zs)  # (n, 3U, k)
        Y = Li @ (JfT @ Gz)
        y = Li @ (JfT @ rr)
        return (Gz.transpose(0, 2, 1) @ rr - Y.transpose(0, 2, 1) @ y)[..., 0]

    return np.concatenate(run_blocks(one, range(len(factors))))


def _sandwich(pr: _Problem, R: np.ndarray, factors: list[tuple], B0: np.ndarray, P: np.ndarray, A: np.ndarray,
              fix_g: np.ndarray, s2: float, frames_per_independent: float) -> np.ndarray:
    """(K, 3, 3) the positive part of each joint's covariance by the sandwich ``B0^-1 (S + P) B0^-1`` less the
    model's own ``B0^-1`` (``B0`` the posterior precision with the frames counted as independent, ``P`` the prior's):
    ``S`` the scores' spread the residuals show, the sum over stretches of ``frames_per_independent``
    consecutive frames of ``s s^T``, ``s`` the stretch's summed score of the constant unknowns with every
    pose eliminated, ``G^T (I - Jf D^-1 Jf^T) r / sigma^2`` per frame. Where the model holds, ``S`` is about
    the data's precision ``H0 / sigma^2`` and the difference about zero. Computed along the joints'
    directions only: the scores times ``B0^-1 A^T``."""
    K = A.shape[0] // 3
    Z = np.linalg.solve(B0, A.T)  # (ng, 3K)
    sc = _scores(pr, R, factors, Z, fix_g) / s2
    block = max(1, int(round(frames_per_independent)))
    sb = np.add.reduceat(sc, np.arange(0, sc.shape[0], block), axis=0)
    full = sb.T @ sb + Z.T @ P @ Z - A @ Z  # (3K, 3K)
    out = full.reshape(K, 3, K, 3)[np.arange(K), :, np.arange(K), :]
    ev, vec = np.linalg.eigh(0.5 * (out + out.transpose(0, 2, 1)))
    return np.einsum("kij,kj,klj->kil", vec, np.maximum(ev, 0.0), vec)  # its positive semi-definite part


def _dof(pr: _Problem) -> tuple[int, int]:
    """(observed coordinates, their degrees of freedom): the coordinates less the unknowns the fit
    had, a segment's rotation in a frame counted where a marker on it or below it is seen, less
    the gauge."""
    w = pr.w[:, pr.used]  # (F, U)
    F = w.shape[0]
    below = np.zeros((pr.used.size, pr.S))
    below[pr.fi, pr.fs] = 1.0  # marker i is on segment s or below it
    active = (w @ below) > 0
    n = 3 * int(w.sum())
    k = 3 * F + 3 * int(active.sum()) + pr.ng - 3 * pr.S - 3
    return n, n - k


def _fitted(parent, origin, marker_segment, marker_local, observed, rot, root_pos, ref_frame: int,
            soft: dict[int, float] | None = None, soft_noise: float = 1.0, chunk: int = 128) -> tuple | None:
    """(problem, bone offsets, marker offsets, rotations, each frame's root origin and soft offsets, degrees of
    freedom, the noise variance the residual measures, the gauge's unknowns, the reduced normal matrix) of a fitted
    skeleton posed on ``observed``; None when the residual leaves no degree of freedom to measure the noise."""
    parent = np.asarray(parent)
    sc = sorted(int(c) for c, v in (soft or {}).items() if parent[int(c)] >= 0 and v > 0)
    pr = _Problem(parent, np.asarray(marker_segment), observed, sc, [soft_noise**2 / soft[c] ** 2 for c in sc])
    if not pr.kids or pr.used.size == 0:
        return None
    d = pr.offsets(origin)
    l = np.array(marker_local, dtype=float)
    R = np.asarray(rot, dtype=float)
    p, soft_dof = pr.soft_offsets(root_pos, R, d, l)
    _, dof = _dof(pr)
    dof -= soft_dof
    cost = pr.cost(p, R, d, l)
    if dof <= 0 or not np.isfinite(cost):
        return None
    s2 = max(cost / dof, 1e-12)
    pr.ws = np.repeat([s2 / soft[c] ** 2 for c in sc], 3)  # the offsets' prior against the noise measured here
    fix_g = _gauge_fixed(pr)
    return pr, d, l, R, p, dof, s2, fix_g, reduced_normal_matrix(pr, p, R, d, l, ref_frame, fix_g, chunk)


def joint_uncertainty(
    parent: np.ndarray,
    origin: np.ndarray,
    marker_segment: np.ndarray,
    marker_local: np.ndarray,
    observed: np.ndarray,
    rot: np.ndarray,
    root_pos: np.ndarray,
    *,
    ref_frame: int,
    prior_scale: float = PRIOR_SCALE,
    chunk: int = 128,
    seed: int = 0,
    frames_per_independent: float = 1.0,
    soft: dict[int, float] | None = None,
    soft_noise: float = 1.0,
) -> JointUncertainty | None:
    """Every joint's posterior uncertainty at a fitted skeleton (see the module docstring).

    parent, origin, marker_segment, marker_local : the skeleton (as
    :func:`~mocapskel.solvers.model.calibrate.refine_skeleton`), its rest pose that of ``ref_frame``.
    observed : (F, M, 3) the markers on the frames of the fit (NaN unseen).
    rot, root_pos : (F, S, 3, 3), (F, 3) the poses fitted to them with this skeleton.
    prior_scale : the prior's standard deviation as a multiple of the child segment's size.
    seed : of the noise draws that measure what the noise alone puts into the curvature.
    frames_per_independent : how many of the fit's frames one independent observation is worth
        (``n / n_eff``, :func:`~mocapskel.solvers.model.effective.effective_frames`): the data's precision is
        divided by it (residuals that stay alike from frame to frame, as skin motion makes them, say less
        than as many independent ones).
    soft : {child: sigma (mm)} the fit's soft joints (their offsets solved again, weighed against ``soft_noise``).

    None when the residual leaves no degree of freedom to measure the noise.
    """
    parent = np.asarray(parent)
    S = len(parent)
    fit = _fitted(parent, origin, marker_segment, marker_local, observed, rot, root_pos, ref_frame, soft, soft_noise, chunk)
    if fit is None:
        return None
    pr, d, l, R, p, dof, s2, fix_g, H0 = fit
    kids = np.array(pr.kids, dtype=int)
    K = kids.size
    size = segment_sizes(parent, origin, marker_segment, marker_local)
    prior_sd = np.maximum(prior_scale * size[kids], 1.0)
    A, frame, frame_markers = _joint_operators(pr, l, d, kids)  # (3K, ng)
    P = (A.T / np.repeat(prior_sd, 3) ** 2) @ A  # the prior's precision over the constant unknowns
    s2p = s2 * max(float(frames_per_independent), 1.0)  # the variance the data's precision is in units of
    B, scale = _gauged(H0 / s2p + P, fix_g)  # the posterior precision before the noise's part is taken out
    # the directions the prior weighs in at all: the data's share rho of the precision along each (the
    # generalized eigenvectors of the data's part against B, B-orthonormal), the 3K where it is least (and the gauge's, of none)
    rho, V = _eigh_generalized(H0 / s2p, B)
    take = np.arange(min(3 * K + int(fix_g.sum()), pr.ng))
    take = take[np.abs(V[np.ix_(~fix_g, take)]).max(0) > 0]  # the gauge's own directions left out
    V, rho = V[:, take], rho[take]
    V[fix_g] = 0.0
    # what the noise alone puts there (see the module docstring), taken out with NOISE_Z of its standard
    # deviations over, and what is left clipped at zero: in that basis, independent of the gauge chosen
    # one pair screens every direction; the rest go to those where the noise's part changes the
    # precision by more than SCREEN (along the others the data outweigh it: left as they are)
    factors = _pose_factors(pr, p, R, d, l, ref_frame, chunk)
    spur, sq = _noise_curvature(pr, R, factors, float(np.sqrt(s2)), V, (seed, 0), 1)
    draws = np.ones(V.shape[1])
    keep = np.flatnonzero(np.diag(spur) > SCREEN * s2p)
    if keep.size and NOISE_PAIRS > 1:
        more, sq_more = _noise_curvature(pr, R, factors, float(np.sqrt(s2)), V[:, keep], (seed, 1), NOISE_PAIRS - 1)
        spur[np.ix_(keep, keep)] = (spur[np.ix_(keep, keep)] + (NOISE_PAIRS - 1) * more) / NOISE_PAIRS
        sq[keep] = (sq[keep] + (NOISE_PAIRS - 1) * sq_more) / NOISE_PAIRS
        draws[keep] = NOISE_PAIRS
    spur, sq = 0.5 * (spur + spur.T) / s2p, sq / s2p**2
    # the spread of that part in the take itself: a sum over frames of parts a frame's noise puts in, each
    # at most one degree of freedom (chi-square: its mean squared is a third of its square's mean), and
    # the spread of its mean over ``draws``
    spread = np.sqrt((2.0 / 3.0) * sq * (1.0 + 1.0 / draws))
    ev, W = np.linalg.eigh(np.diag(rho) - spur - NOISE_Z * np.diag(spread))
    M = (W * np.maximum(ev, 0.0)) @ W.T
    BV = B @ V
    lam = B + BV @ (M - np.diag(rho)) @ BV.T
    Z = np.linalg.solve(lam, A.T)  # (ng, 3K)
    C = (A @ Z).reshape(K, 3, K, 3)
    cov = C[np.arange(K), :, np.arange(K), :]  # (K, 3, 3)
    cov = 0.5 * (cov + cov.transpose(0, 2, 1))
    # what the residuals themselves show beyond the model's noise (the sandwich; see the module docstring)
    B0, _ = _gauged(H0 / s2 + P, fix_g, scale)
    spread = _sandwich(pr, R, factors, B0, P, A, fix_g, s2, frames_per_independent)
    sd, directions = _principal(cov)
    share = np.clip(sd**2 / prior_sd[:, None] ** 2, 0.0, 1.0)
    turned, lacks = _axes(pr, R, l, kids, directions[:, 0])
    return JointUncertainty(
        kids=kids, cov=cov, spread=spread, sd=sd, directions=directions, prior_share=share, prior_sd=prior_sd,
        frame=frame, frame_markers=frame_markers, turned_about=turned, lacks_axis=lacks,
        noise_sd=float(np.sqrt(s2)), dof=int(dof), frames=int(p.shape[0]), soft=tuple(pr.soft), pose_p=p,
    )


def _principal(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(K, 3) standard deviations, largest first, and (K, 3, 3) their unit directions (rows) of covariances
    (K, 3, 3), each direction's largest component positive (a stable, readable sign)."""
    ev, vec = np.linalg.eigh(cov)
    ev, vec = np.maximum(ev[:, ::-1], 0.0), vec[:, :, ::-1]
    directions = vec.transpose(0, 2, 1)
    big = np.take_along_axis(directions, np.abs(directions).argmax(2)[..., None], 2)[..., 0]
    return np.sqrt(ev), directions * np.where(big < 0, -1.0, 1.0)[..., None]


def _axes(pr: _Problem, R: np.ndarray, l: np.ndarray, kids: np.ndarray, free: np.ndarray
          ) -> tuple[np.ndarray, np.ndarray]:
    """Per joint, the main axis of its relative rotations over the frames (the right singular vector
    of their rotation vectors of the largest singular value), and the axis across both ``free`` (its
    least fixed direction) and the child's bone, about which a turn would fix it."""
    K = kids.size
    rel = np.swapaxes(R[:, pr.parent[kids]], -1, -2) @ R[:, kids]  # (F, K, 3, 3)
    rv = matrix_to_rotvec(rel.reshape(-1, 3, 3)).reshape(-1, K, 3)
    turned = np.full((K, 3), np.nan)
    ok = np.isfinite(rv).all(-1)
    for k in range(K):
        x = rv[ok[:, k], k]
        if x.shape[0] >= 3 and np.abs(x).max() > 0:
            v = np.linalg.svd(x, full_matrices=False)[2][0]
            turned[k] = v * (1.0 if v[np.abs(v).argmax()] >= 0 else -1.0)
    lacks = np.zeros((K, 3))
    for k, c in enumerate(kids):
        ms = [int(m) for m in pr.used if pr.seg[m] == c]
        bone = l[ms].mean(0) if ms else np.zeros(3)
        u = free[k]
        w = np.cross(u, bone)
        if np.linalg.norm(w) < 1e-6 * max(np.linalg.norm(bone), 1e-300) or not np.linalg.norm(bone) > 0:
            e = np.eye(3)[np.argmin(np.abs(u))]
            w = np.cross(u, e)
        w = w / np.linalg.norm(w)
        lacks[k] = w * (1.0 if w[np.abs(w).argmax()] >= 0 else -1.0)
    return turned, lacks


def skeleton_uncertainty(skel) -> dict | None:
    """The uncertainty of every joint of a fitted skeleton (a ``Skeleton``), JSON-able, or None when the
    skeleton carries no poses of a refinement to measure it on.

    The poses are those of the refinement's frames, as the fit left them. Keys: ``prior`` (its scale and the threshold of ``set_by_prior``),
    ``noise_mm`` and ``dof`` (the take's noise from the fit's residual), ``frames``, ``skin_share`` (the share
    of the residual the joint angles explain, :class:`~mocapskel.solvers.model.skin.SkinMotion`: skin that slides
    with the joints, which the noise above does not describe; None where it cannot be measured), ``seconds`` and
    ``joints``: {child segment name: {sd_mm, directions, skin_sd_mm, prior_share, prior_sd_mm, set_by_prior,
    frame, frame_markers, turned_about, lacks_rotation_about}} (directions and axes in the lab's axes at the
    rest frame; ``lacks_rotation_about`` None unless set by the prior). ``sd_mm`` and ``directions`` are the
    principal axes of the model's posterior covariance plus the residuals' own spread (the sandwich's
    excess, see the module docstring) plus ``skin_sd_mm``^2 I, how far skin that slides with
    the joint's angle can have moved it unseen (:meth:`~mocapskel.solvers.model.skin.SkinMotion.joint_sd`);
    ``prior_share`` is the prior's share of the model's precision along each of them.
    """
    t = time.perf_counter()
    if skel.pose_rot is None or skel.pose_frames is None or skel.joints is None:
        return None
    pts = skel.joints.topology.segments.markers.points[skel.pose_frames]
    rot, root = skel.pose_rot, skel.pose_root
    ref = int(np.searchsorted(skel.pose_frames, skel.rest_frame))
    if not (ref < skel.pose_frames.size and skel.pose_frames[ref] == skel.rest_frame):
        return None
    fit = skel.info.get("refined") or {}
    soft = {skel.names.index(n): v for n, v in (fit.get("soft_sigma_mm") or {}).items()}
    u = joint_uncertainty(skel.parent, skel.origin, skel.marker_segment, skel.marker_local, pts, rot, root,
                          ref_frame=ref, frames_per_independent=frames_per_independent(skel), soft=soft,
                          soft_noise=float(fit.get("soft_noise_mm", 1.0)))
    if u is None:
        return None
    skin = skin_motion(skel.parent, skel.marker_segment, skel.origin, skel.marker_local, pts, rot, u.pose_p, u.soft)
    # at most the joint's largest sd of the model: skin cannot leave it surer, and a joint that barely turns
    # (a reach's still leg) shows too little of its skin's curve to say more
    skin_sd = np.zeros(len(skel.parent))
    skin_sd[u.kids] = np.minimum(skin.joint_sd(skel.parent)[u.kids], u.sd[:, 0])
    sd, directions = _principal(u.cov + u.spread + (skin_sd[u.kids] ** 2)[:, None, None] * np.eye(3))
    # the prior's share along those directions, of the model's own precision (the skin's part and the
    # residuals' spread are no prior's)
    lam = np.einsum("kai,kij,kaj->ka", directions, np.linalg.pinv(u.cov), directions)
    prior_share = np.clip((1.0 / u.prior_sd[:, None] ** 2) / np.maximum(lam, 1e-300), 0.0, 1.0)
    joints = {}
    for k, c in enumerate(u.kids.tolist()):
        prior_set = bool(u.set_by_prior[k])
        joints[skel.names[c]] = {
            "sd_mm": [round(float(x), 3) for x in sd[k]],
            "directions": np.round(directions[k], 4).tolist(),
            "skin_sd_mm": round(float(skin_sd[c]), 2),
            "prior_share": [round(float(x), 4) for x in prior_share[k]],
            "prior_sd_mm": round(float(u.prior_sd[k]), 1),
            "set_by_prior": prior_set,
            "frame": skel.names[int(u.frame[k])],
            "frame_markers": int(u.frame_markers[k]),
            "turned_about": None if not np.isfinite(u.turned_about[k]).all() else np.round(u.turned_about[k], 4).tolist(),
            "lacks_rotation_about": np.round(u.lacks_axis[k], 4).tolist() if prior_set else None,
        }
    share = skin.share
    return {"prior": {"sd_per_segment_size": PRIOR_SCALE, "set_by_prior_above": SET_BY_PRIOR},
            "noise_mm": round(u.noise_sd, 4), "dof": u.dof, "frames": u.frames,
            "skin_share": round(float(share), 3) if np.isfinite(share) else None,
            "seconds": round(time.perf_counter() - t, 4), "joints": joints}


def _eigh_generalized(A: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eigenvalues (ascending) and B-orthonormal eigenvectors of ``A v = w B v`` (A symmetric, B
    positive definite), by B's Cholesky factor: what ``scipy.linalg.eigh(A, B)`` gives, without
    importing scipy.linalg (a fifth of a second) on every fit."""
    L = np.linalg.cholesky(B)
    Li = np.linalg.solve(L, np.eye(L.shape[0]))
    C = Li @ A @ Li.T
    w, W = np.linalg.eigh(0.5 * (C + C.T))
    return w, Li.T @ W
