"""A skeleton as a BVH file holds it: its HIERARCHY (:class:`BvhSkeleton`), forward kinematics, the lab's axes
and units turned into the file's, and the choice of Euler order (see :mod:`mocapskel.io.bvh` for the conventions)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, overload

import numpy as np

from .parallel import n_threads, run_blocks
from .rotations import ORDERS, _parse_order
from .euler_continuity import RestSteps, order_spike_counts


#: Length of one output unit in mm (mocapskel's internal unit).
UNIT_SCALE: dict[str, float] = {"mm": 1.0, "cm": 10.0, "m": 1000.0}


#: Lab -> BVH axes for each ``--up``: BVH coordinates = AXES[up] @ lab coordinates.
_AXES: dict[str, np.ndarray] = {
    "z": np.eye(3),
    "y": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]),
}


@dataclass(frozen=True, eq=False)
class BvhSkeleton:
    """The HIERARCHY part of a BVH file.

    Attributes
    ----------
    names : tuple of str, length S
        Joint names.
    parent : (S,) int ndarray
        Parent joint, -1 for the root; the root is joint 0 and every parent
        precedes its children.
    offset : (S, 3) float ndarray
        OFFSET of each joint from its parent in the parent's rest frame (the
        root's: its rest position).
    end_site : (S, 3) float ndarray
        End Site offset of each leaf (ignored for inner joints; a zero one is
        replaced by a default when written, see :func:`~mocapskel.io.bvh.write_bvh`).
    order : str
        Rotation channel order, e.g. ``"ZXY"`` for ``Zrotation Xrotation Yrotation``.
    """

    names: tuple[str, ...]
    parent: np.ndarray
    offset: np.ndarray
    end_site: np.ndarray
    order: str = "ZXY"

    def __post_init__(self) -> None:
        names = tuple(str(n) for n in self.names)
        parent = np.asarray(self.parent, dtype=np.int64).reshape(-1)
        S = len(names)
        offset = np.asarray(self.offset, dtype=np.float64)
        end_site = np.asarray(self.end_site, dtype=np.float64)
        _parse_order(self.order)
        if S == 0:
            raise ValueError("a skeleton needs at least one joint")
        if parent.shape != (S,) or offset.shape != (S, 3) or end_site.shape != (S, 3):
            raise ValueError(
                f"names ({S}), parent {parent.shape}, offset {offset.shape} and end_site "
                f"{end_site.shape} must describe the same S joints: (S,), (S, 3), (S, 3)"
            )
        if parent[0] != -1 or np.any(parent[1:] < 0) or np.any(parent[1:] >= np.arange(1, S)):
            raise ValueError("parent must be -1 for joint 0 only, and every parent must precede its child")
        if not (np.isfinite(offset).all() and np.isfinite(end_site).all()):
            raise ValueError("offsets and end sites must be finite")
        object.__setattr__(self, "names", names)
        object.__setattr__(self, "parent", parent)
        object.__setattr__(self, "offset", offset)
        object.__setattr__(self, "end_site", end_site)
        object.__setattr__(self, "order", self.order.upper())

    @property
    def n_joints(self) -> int:
        """S, the number of joints."""
        return len(self.names)

    @property
    def is_leaf(self) -> np.ndarray:
        """(S,) bool, joints without children."""
        leaf = np.ones(self.n_joints, dtype=bool)
        leaf[self.parent[self.parent >= 0]] = False
        return leaf


@overload
def forward_kinematics(
    skel: BvhSkeleton, root_pos: np.ndarray, local_rot: np.ndarray, *, with_rot: Literal[False] = False
) -> np.ndarray: ...


@overload
def forward_kinematics(
    skel: BvhSkeleton, root_pos: np.ndarray, local_rot: np.ndarray, *, with_rot: Literal[True]
) -> tuple[np.ndarray, np.ndarray]: ...


def forward_kinematics(
    skel: BvhSkeleton, root_pos: np.ndarray, local_rot: np.ndarray, *, with_rot: bool = False
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """World joint positions of a BVH motion (vectorised over frames).

    Parameters
    ----------
    skel : BvhSkeleton
    root_pos : (F, 3) array_like
        Root position per frame.
    local_rot : (F, S, 3, 3) array_like
        Rotation of each joint relative to its parent.
    with_rot : bool
        Also return the global rotations.

    Returns
    -------
    pos : (F, S, 3) ndarray
        ``pos[:, 0] = root_pos``; ``pos[:, s] = pos[:, p] + G[:, p] @ offset[s]``.
    rot : (F, S, 3, 3) ndarray
        Global rotations ``G[:, s] = G[:, p] @ local_rot[:, s]`` (only with ``with_rot``).
    """
    root_pos = np.asarray(root_pos, dtype=np.float64)
    local_rot = np.asarray(local_rot, dtype=np.float64)
    F, S = local_rot.shape[:2]
    if S != skel.n_joints or root_pos.shape != (F, 3) or local_rot.shape[2:] != (3, 3):
        raise ValueError(f"need root_pos (F, 3) and local_rot (F, {skel.n_joints}, 3, 3), "
                         f"got {root_pos.shape} and {local_rot.shape}")
    G = np.empty_like(local_rot)
    P = np.empty((F, S, 3))
    G[:, 0] = local_rot[:, 0]
    P[:, 0] = root_pos
    for s in range(1, S):
        p = skel.parent[s]
        G[:, s] = G[:, p] @ local_rot[:, s]
        P[:, s] = P[:, p] + G[:, p] @ skel.offset[s]
    return (P, G) if with_rot else P


def global_to_local_rot(parent: np.ndarray, rot: np.ndarray) -> np.ndarray:
    """Parent-relative rotations from global ones: ``L[s] = G[parent]^T G[s]``.

    With mocapskel's convention (rest pose axes = lab axes, ``Motion.rot``
    global rotations relative to rest), this gives BVH ``local_rot`` whose
    rest pose (all channels zero) is the subject at the rest frame.

    Parameters
    ----------
    parent : (S,) int array_like
        -1 for the root.
    rot : (F, S, 3, 3) array_like
        Global rotations.

    Returns
    -------
    local : (F, S, 3, 3) ndarray
        Stored as ``rot`` is. The products are written out entry by entry,
        joint by joint, into the result: on the frames-innermost arrays of
        :func:`lab_rot_to_bvh` several times faster than a batched ``@`` of
        3x3 matrices (and equal to it within a unit in the last place).
    """
    parent = np.asarray(parent, dtype=np.int64)
    rot = np.asarray(rot, dtype=np.float64)
    local = np.empty_like(rot)  # order "K": the layout of rot; every entry is written below
    root = np.flatnonzero(parent < 0)
    local[:, root] = rot[:, root]

    def joints(which: np.ndarray) -> None:  # each joint writes its own entries: halves side by side
        tmp = np.empty(rot.shape[0])
        for s in which:
            G, P = rot[:, s], rot[:, parent[s]]
            for i in range(3):
                for j in range(3):
                    out = local[:, s, i, j]
                    np.multiply(P[:, 0, i], G[:, 0, j], out=out)
                    out += np.multiply(P[:, 1, i], G[:, 1, j], out=tmp)
                    out += np.multiply(P[:, 2, i], G[:, 2, j], out=tmp)

    kids = np.flatnonzero(parent >= 0)
    half = (kids.size + 1) // 2
    run_blocks(joints, [kids[:half], kids[half:]])
    return local


def local_to_global_rot(parent: np.ndarray, local_rot: np.ndarray) -> np.ndarray:
    """Global rotations from parent-relative ones (parents must precede children).

    Parameters
    ----------
    parent : (S,) int array_like
        -1 for the root.
    local_rot : (F, S, 3, 3) array_like

    Returns
    -------
    rot : (F, S, 3, 3) ndarray
    """
    parent = np.asarray(parent, dtype=np.int64)
    G = np.array(local_rot, dtype=np.float64)
    for s in range(G.shape[1]):
        if parent[s] >= 0:
            G[:, s] = G[:, parent[s]] @ G[:, s]
    return G


def _axes(up: str) -> np.ndarray:
    if up not in _AXES:
        raise ValueError(f"up must be 'y' or 'z', got {up!r}")
    return _AXES[up]


def _signed_permutation(C: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``C @ p == p[perm] * sign`` for a signed permutation matrix (keeps NaN per component)."""
    perm = np.argmax(np.abs(C), axis=1)
    return perm, C[np.arange(3), perm]


def _scale(units: str) -> float:
    if units not in UNIT_SCALE:
        raise ValueError(f"units must be one of {sorted(UNIT_SCALE)}, got {units!r}")
    return UNIT_SCALE[units]


def lab_to_bvh(points: np.ndarray, up: str = "y", units: str = "cm") -> np.ndarray:
    """Lab coordinates (mm) to BVH coordinates.

    ``up="z"``: axes unchanged; ``up="y"``: lab (x, y, z) -> BVH (x, z, -y), a
    proper rotation (det +1) after which Blender's default BVH import (Y up)
    puts the subject back in its lab frame. Then mm -> ``units``. NaN stays NaN.

    Parameters
    ----------
    points : (..., 3) array_like
        Positions or offsets in the lab frame, mm.
    up : {"y", "z"}
    units : {"cm", "mm", "m"}

    Returns
    -------
    (..., 3) ndarray
    """
    perm, sign = _signed_permutation(_axes(up))
    return np.asarray(points, dtype=np.float64)[..., perm] * (sign / _scale(units))


def bvh_to_lab(points: np.ndarray, up: str = "y", units: str = "cm") -> np.ndarray:
    """Inverse of :func:`lab_to_bvh`: BVH coordinates in ``units`` to lab mm.

    Parameters
    ----------
    points : (..., 3) array_like
    up : {"y", "z"}
    units : {"cm", "mm", "m"}

    Returns
    -------
    (..., 3) ndarray
    """
    perm, sign = _signed_permutation(_axes(up).T)
    return np.asarray(points, dtype=np.float64)[..., perm] * (sign * _scale(units))


def _permute_rot(R: np.ndarray, C: np.ndarray, joints: np.ndarray | None = None) -> np.ndarray:
    """``C R C^T`` for a signed permutation ``C``, entry by entry (see :func:`lab_rot_to_bvh`)."""
    perm, sign = _signed_permutation(C)
    R = np.asarray(R, dtype=np.float64)
    if R.shape[-2:] != (3, 3):
        raise ValueError(f"R must have shape (..., 3, 3), got {R.shape}")
    entry = (3 * perm[:, None] + perm[None, :]).ravel()  # C R C^T [i, j] = sign_i sign_j R[perm_i, perm_j]
    flip = np.outer(sign, sign).ravel()
    if joints is not None:
        joints = np.asarray(joints, dtype=np.int64)
    if R.ndim < 4 or R.shape[0] == 0:  # no joint axis, or nothing to lay out
        if joints is not None:
            R = R[:, joints]
        return (R.reshape(R.shape[:-2] + (9,))[..., entry] * flip).reshape(R.shape)
    F, lead = R.shape[0], R.shape[1:-2]
    mats = np.arange(int(np.prod(lead, dtype=np.int64))).reshape(lead)
    if joints is not None:
        mats = mats[joints]
    take = (9 * mats.reshape(-1, 1) + entry).ravel()
    out = _transpose_blocks(np.ascontiguousarray(R).reshape(F, -1), take, np.tile(flip, mats.size))
    return np.moveaxis(out.reshape(mats.shape + (3, 3, F)), -1, 0)


def lab_rot_to_bvh(R: np.ndarray, up: str = "y", *, joints: np.ndarray | None = None) -> np.ndarray:
    """Rotations expressed in the lab frame to the BVH frame: ``C R C^T``.

    Parameters
    ----------
    R : (F, ..., 3, 3) array_like
    up : {"y", "z"}
    joints : (S',) int array_like, optional
        Keep only these indices of axis 1, in this order (``R[:, joints]``,
        without copying ``R`` first).

    Returns
    -------
    (F, ..., 3, 3) ndarray
        Exactly the values of ``C @ R @ C.T`` (every entry is an entry of
        ``R`` times +-1; NaN stays in its own entry), stored with the frame
        axis innermost so that :func:`global_to_local_rot` and the BVH writer
        read contiguous series over frames.
    """
    return _permute_rot(R, _axes(up), joints)


def bvh_rot_to_lab(R: np.ndarray, up: str = "y") -> np.ndarray:
    """Inverse of :func:`lab_rot_to_bvh`: ``C^T R C``.

    Parameters
    ----------
    R : (F, ..., 3, 3) array_like
    up : {"y", "z"}

    Returns
    -------
    (F, ..., 3, 3) ndarray
        Stored as :func:`lab_rot_to_bvh` stores its result.
    """
    return _permute_rot(R, _axes(up).T)


def gimbal_margin(local_rot: np.ndarray) -> np.ndarray:
    """How far each joint stays from gimbal lock in each rotation order, over a take.

    With order (i, j, k) the middle angle ``b`` has ``sin b = ±R[i, k]``, and the
    Euler angles turn ``1 / cos b`` times faster than the rotation (near lock a
    1-degree turn can swing the outer angles by tens of degrees). The margin is
    ``90 - max |b|`` over frames.

    Parameters
    ----------
    local_rot : (F, S, 3, 3) array_like

    Returns
    -------
    (S, 6) ndarray
        Degrees, columns in :data:`~mocapskel.solvers.rotations.ORDERS` order.
    """
    R = np.asarray(local_rot, dtype=np.float64)
    S = R.shape[1]
    out = np.empty((S, len(ORDERS)))
    if R.shape[0] == 0:
        out[:] = 90.0
        return out
    top = np.maximum(R.max(axis=0), -R.min(axis=0))  # (S, 3, 3): the largest |R[i, k]| over frames (no copy of R)
    for n, order in enumerate(ORDERS):
        i, _, k, _ = _parse_order(order)
        out[:, n] = 90.0 - np.degrees(np.arcsin(np.clip(top[:, i, k], 0.0, 1.0)))
    return out


def near_lock_counts(local_rot: np.ndarray, within_deg: float = 20.0) -> np.ndarray:
    """(6,) joint-frames whose middle angle comes within ``within_deg`` of gimbal lock, per order
    (:data:`~mocapskel.solvers.rotations.ORDERS`); there the Euler angles turn more than
    ``1 / sin(within_deg)`` times faster than the rotation."""
    R = np.asarray(local_rot, dtype=np.float64)
    lim = np.cos(np.radians(within_deg))  # |sin b| above this
    out = np.zeros(len(ORDERS), dtype=np.int64)
    for n, order in enumerate(ORDERS):
        i, _, k, _ = _parse_order(order)
        x = R[..., i, k]
        out[n] = int(np.count_nonzero(x > lim) + np.count_nonzero(x < -lim))
    return out


def choose_rotation_order(local_rot: np.ndarray, preferred: str = "ZXY", min_margin_deg: float = 30.0,
                          near_deg: float = 20.0, spikes: np.ndarray | None = None) -> str:
    """One rotation order for every joint of a take, with the fewest Euler spikes.

    The order whose channels step more than the joints turn plus a few degrees
    (:func:`~mocapskel.solvers.euler_continuity.order_spike_counts`) at the
    fewest joint-frames; among those ``preferred`` when every joint stays at
    least ``min_margin_deg`` from gimbal lock in it (the Euler angles then turn
    at most twice as fast as the rotation), else the one with the fewest
    joint-frames within ``near_deg`` of lock (:func:`near_lock_counts`), then
    the one whose closest joint stays farthest from lock, ``preferred`` first
    among equals. See :func:`gimbal_margin`. ``spikes``: the counts of
    :func:`~mocapskel.solvers.euler_continuity.order_spike_counts`, when known.
    """
    pref = preferred.upper()
    _parse_order(pref)
    R = np.asarray(local_rot)
    if R.shape[0] == 0 or R.shape[1] == 0:
        return pref
    worst = gimbal_margin(R).min(axis=0)
    spikes = order_spike_counts(R) if spikes is None else np.asarray(spikes)
    near = near_lock_counts(R, near_deg)
    p = ORDERS.index(pref)
    cands = [pref] + [o for o in ORDERS if o != pref]

    def key(o: str) -> tuple:
        n = ORDERS.index(o)
        return (spikes[n], not (n == p and worst[n] >= min_margin_deg), near[n], -worst[n])

    return min(cands, key=key)


def rerest_local(parent: np.ndarray, local: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """Parent-relative rotations after the rest pose is turned by ``Q``: ``Q[p] L Q[s]^T`` (the root: ``L Q[root]^T``).

    Parameters
    ----------
    parent : (S,) int array_like
        -1 for the root.
    local : (F, S, 3, 3) array_like
    Q : (S, 3, 3) array_like
        Each joint's global rotation from the old rest pose to the new one (e.g. the global
        rotations of a frame, which makes that frame's pose the rest).
    """
    parent = np.asarray(parent, dtype=np.int64)
    Q = np.asarray(Q, dtype=np.float64)
    local = np.asarray(local, dtype=np.float64)
    Qp = np.where((parent >= 0)[:, None, None], Q[np.maximum(parent, 0)], np.eye(3))
    F = local.shape[0]
    out = np.empty_like(local)  # the layout of local (frames innermost from lab_rot_to_bvh)
    for s in range(parent.size):
        # Q[p] L Q[s]^T is linear in L's 9 entries: one (9, 9) x (9, F) product per joint
        K = np.kron(Qp[s], Q[s])
        src, dst = local[:, s].transpose(1, 2, 0), out[:, s].transpose(1, 2, 0)
        if src.flags.c_contiguous and dst.flags.c_contiguous:
            np.matmul(K, src.reshape(9, F), out=dst.reshape(9, F))
        else:
            dst[...] = (K @ src.reshape(9, F)).reshape(3, 3, F)
    return out


def _count_every_step(L: np.ndarray, parent: np.ndarray, Q: np.ndarray, orders: tuple[str, ...],
                      chunk: int = 8192) -> tuple[np.ndarray, np.ndarray]:
    """:meth:`RestSteps.count` over every step of ``L``, ``chunk`` steps at a time (bounded memory)."""
    F = L.shape[0]
    sp = np.zeros((Q.shape[0], len(orders)), dtype=np.int64)
    nr = np.zeros_like(sp)
    for a in range(0, F - 1, chunk):
        s, r = RestSteps(L[a : a + chunk + 1], parent).count(Q, orders)
        sp += s
        nr += r
    return sp, nr


def choose_rest_and_order(local: np.ndarray, parent: np.ndarray, frames: np.ndarray, keep: int,
                          orders: tuple[str, ...] = ORDERS, n_rests: int = 64, batch: int = 8,
                          n_steps: int = 2048, n_final: int = 3) -> tuple[int, str]:
    """The rest frame and the rotation order of the fewest Euler spikes, chosen together.

    Taking frame r's pose as the rest turns every joint's rotation into
    ``Q[p] L Q[s]^T`` with Q the global rotations of frame r: its turns stay, its
    path moves relative to the orders' gimbal-lock surfaces (the middle angle at
    +-90 degrees, where the outer angles turn 1 / sin(distance) faster than the
    joint). ``keep`` (``local``'s own rest) is counted first, in every order of
    ``orders``, on every step; with no spike in some order it stays, in the
    order :func:`choose_rotation_order` takes. Else up to ``n_rests`` of
    ``frames``, spread evenly over them, are tried ``batch`` at a time (each
    batch spread over the take), in every order
    (:meth:`~mocapskel.solvers.euler_continuity.RestSteps.count`), on at most
    ``n_steps`` frame steps spread over the take; the ``n_final`` best pairs of
    a batch are counted on every step (unless their sampled steps, a part of all,
    already spike as often as the best so far), and the search stops at the first
    pair with no spike. Among pairs: fewest spikes, then ``keep``, then the fewest
    steps near lock.

    Parameters
    ----------
    local : (F, S, 3, 3) array_like
        Rotations relative to the parents, with ``keep``'s pose as the rest.
    parent : (S,) int array_like
        -1 for the root; parents precede children.
    frames : (K,) int array_like
        The frames whose pose may be the rest (e.g. those where the whole subject is seen).
    keep : int
        The frame of ``local``'s own rest pose.
    orders : tuple of str
        The orders to choose from.

    Returns
    -------
    (frame, order)
    """
    L = np.asarray(local, dtype=np.float64)
    parent = np.asarray(parent, dtype=np.int64)
    F = L.shape[0]
    sp = order_spike_counts(L)[[ORDERS.index(o) for o in orders]]
    if sp.min() == 0 or F < 2:
        return int(keep), (choose_rotation_order(L, spikes=sp) if len(orders) == len(ORDERS) else orders[int(np.argmin(sp))])
    n = int(np.argmin(sp))
    best = ((int(sp[n]), False, 0), int(keep), orders[n])
    L = np.ascontiguousarray(L)  # frames outermost: the steps below are read frame by frame
    frames = np.unique(np.asarray(frames, dtype=np.int64))
    frames = frames[(frames >= 0) & (frames < F) & (frames != keep)]
    if frames.size > n_rests:
        frames = frames[np.round(np.linspace(0, frames.size - 1, n_rests)).astype(np.int64)]
    exact = F - 1 <= n_steps
    sampled = RestSteps(L, parent, None if exact else np.unique(np.linspace(0, F - 2, n_steps).astype(np.int64)))
    n_batches = max(1, -(-frames.size // batch))
    for b in range(n_batches):
        rests = frames[b::n_batches]
        if rests.size == 0:
            continue
        Q = local_to_global_rot(parent, L[rests])
        sp, nr = sampled.count(Q, orders)
        picks = [divmod(kn, len(orders)) for kn in np.lexsort((nr.ravel(), sp.ravel()))[: 1 if exact else n_final].tolist()]

        def worse(k: int, n: int) -> bool:  # its sampled steps, a part of all, already spike as often as the best on all
            return not exact and (sp[k, n] > best[0][0] or (sp[k, n] == best[0][0] and not best[0][1]))

        if not exact:  # the picks the best so far does not rule out, counted on every step in one pass
            todo = [(k, n) for k, n in picks if not worse(k, n)]
            ks, ns = sorted({k for k, _ in todo}), sorted({n for _, n in todo})
            if todo:
                full = _count_every_step(L, parent, Q[ks], tuple(orders[n] for n in ns))
        for k, n in picks:
            if worse(k, n):
                continue
            s_, r_ = (sp[k, n], nr[k, n]) if exact else (x[ks.index(k), ns.index(n)] for x in full)
            cand = ((int(s_), True, int(r_)), int(rests[k]), orders[n])
            if cand[0] < best[0]:
                best = cand
        if best[0][0] == 0:
            break
    return best[1], best[2]


_CACHE_FRAMES = 512  # frames per block of a transposing copy (see _transpose_blocks)


def _transpose_blocks(flat: np.ndarray, take: np.ndarray | None = None, scale: np.ndarray | None = None) -> np.ndarray:
    """The (F, K) array ``flat`` (optionally ``flat[:, take] * scale``) transposed to a new (K, F) array.

    Copied a few hundred frames at a time, so that each block stays in the
    cache: about twice as fast as one transposing copy of a long take.
    """
    F = flat.shape[0]
    out = np.empty((flat.shape[1] if take is None else take.size, F))

    def part(starts: range) -> None:  # parts of the take write their own frames: side by side on the cores
        for f in starts:
            blk = flat[f : f + _CACHE_FRAMES]
            if take is not None:
                blk = np.take(blk, take, axis=1)
            if scale is not None:
                blk = blk * scale
            out[:, f : f + _CACHE_FRAMES] = blk.T

    n = -(-F // _CACHE_FRAMES)
    k = max(1, min(n_threads(), n // 8))  # a part of at least 8 blocks
    run_blocks(part, [range(_CACHE_FRAMES * (n * i // k), min(F, _CACHE_FRAMES * (n * (i + 1) // k)), _CACHE_FRAMES)
                      for i in range(k)])
    return out
