"""BVH: write files the way importers want them, read any BVH back.

What :func:`write_bvh` writes (DESIGN, "BVH the way importers want it"):

- one ROOT with 6 channels, ``Xposition Yposition Zposition`` then the three
  rotations; every JOINT exactly 3 rotation channels; one rotation order
  everywhere (default ``Zrotation Xrotation Yrotation``);
- joints depth first, children in index order;
- names that match ``[A-Za-z_][A-Za-z0-9_]*``, unique, none a prefix of
  another (:func:`sanitize_names` makes any list so);
- every leaf with a non-zero End Site;
- ``Frames:`` the number of frames, ``Frame Time:`` with 10 significant digits
  (at least 8 decimals) so that ``1 / Frame Time`` is the rate (:func:`format_frame_time`);
- Euler angles continuous frame to frame (:func:`~mocapskel.solvers.rotations.unwrap_euler`);
- no NaN: missing frames must be filled by the caller;
- atomically: a temporary file beside the target, renamed when complete.

Conventions (shared by the writer, the reader and :func:`forward_kinematics`):
``local_rot[f, s]`` is joint ``s``'s rotation relative to its parent, the
product of its rotation channels in channel order (intrinsic, see
:mod:`mocapskel.solvers.rotations`); the root's position channels are its
absolute position and replace its OFFSET (Blender, bvhio and the common
parsers read them so; parsers that add the two agree when the root OFFSET is
zero). Joint ``s`` sits at ``pos[parent] + G[parent] @ offset[s]`` with
``G`` the global (accumulated) rotations.

Coordinates: mocapskel works in the lab frame in mm; :func:`lab_to_bvh` and
:func:`lab_rot_to_bvh` apply the ``--up``/``--units`` rules (up z: axes as in
the lab; up y: lab (x, y, z) -> BVH (x, z, -y)). From a ``Motion`` (global
rotations relative to a rest pose whose axes are the lab axes) the BVH
arguments are::

    offset    = lab_to_bvh(skeleton.offset, up, units)
    root_pos  = lab_to_bvh(motion.root_pos, up, units)
    local_rot = global_to_local_rot(skeleton.parent, lab_rot_to_bvh(motion.rot, up))

and the rest pose (all channels zero) is the subject at the rest frame.
"""
from __future__ import annotations

import math
import os
import re
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Literal, overload

import numpy as np

from ..errors import InputError
from ..solvers.rotations import _parse_order, euler_to_matrix, matrix_to_euler, unwrap_euler
from .atomic import atomic_open

__all__ = [
    "BvhSkeleton",
    "NAME_PATTERN",
    "check_names",
    "sanitize_names",
    "depth_first_order",
    "bvh_text",
    "format_frame_time",
    "write_bvh",
    "read_bvh",
    "parse_bvh",
    "forward_kinematics",
    "global_to_local_rot",
    "local_to_global_rot",
    "lab_to_bvh",
    "bvh_to_lab",
    "lab_rot_to_bvh",
    "bvh_rot_to_lab",
    "UNIT_SCALE",
]

#: A valid BVH joint name (the whole name must match).
NAME_PATTERN = re.compile(r"[A-Za-z_][A-Za-z0-9_]*\Z")

#: Length of one output unit in mm (mocapskel's internal unit).
UNIT_SCALE: dict[str, float] = {"mm": 1.0, "cm": 10.0, "m": 1000.0}

#: Lab -> BVH axes for each ``--up``: BVH coordinates = AXES[up] @ lab coordinates.
_AXES: dict[str, np.ndarray] = {
    "z": np.eye(3),
    "y": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]),
}

# Formatting the MOTION block is the writer's hot spot. Measured on 60,000
# frames x 51 channels (CPU time, 2-core machine, CPython 3.11, numpy 2):
# np.savetxt 0.69 s; one '%' over the whole motion 0.91 s; '" ".join(map(fmt,
# row))' per row 1.03 s; '%' per block of 4096 rows 0.58 s; digits written
# by numpy into a byte grid per block of 4096 rows, padding dropped by a
# boolean mask, 0.19 s; the same grid with the padding dropped by
# bytes.translate 0.13 s; at 6 decimals, two 64-bit words per number from
# 3-digit tables (_format_p6), per block of 1024 rows, 0.09 s. All
# byte-identical to '%.{p}f' (tests check it). Whole write_bvh of a solved
# 60,000-frame take (15 joints): 0.64 s before, 0.36 s now, of which
# matrix_to_euler and unwrap_euler take about 0.2 s.
_BLOCK_FRAMES = 1024
_CACHE_FRAMES = 512  # frames per block of a transposing copy (see _transpose_blocks)
_CHECK_FRAMES = 4096  # frames per block of the rotation check


# --------------------------------------------------------------------------- skeleton


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
        replaced by a default when written, see :func:`write_bvh`).
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


def depth_first_order(parent: np.ndarray) -> np.ndarray:
    """The order in which a BVH file lists the joints of a tree.

    Parameters
    ----------
    parent : (S,) int array_like
        -1 for the root(s); any numbering (parents need not come first).

    Returns
    -------
    order : (S,) int ndarray
        Joint indices depth first from the root, children in index order, so
        every parent comes before its children. It is ``arange(S)`` when the
        skeleton is already in that order, as every skeleton :func:`read_bvh`
        returns is.
    """
    parent = np.asarray(parent, dtype=np.int64)
    children: list[list[int]] = [[] for _ in range(len(parent))]
    for s in range(len(parent)):
        if parent[s] >= 0:
            children[parent[s]].append(s)
    out: list[int] = []
    stack = [int(r) for r in np.flatnonzero(parent < 0)[::-1]]
    while stack:
        s = stack.pop()
        out.append(s)
        stack.extend(reversed(children[s]))
    return np.asarray(out, dtype=np.int64)


# --------------------------------------------------------------------------- names


def check_names(names: Sequence[str]) -> None:
    """Raise ValueError unless ``names`` are valid BVH joint names.

    Valid: each matches ``[A-Za-z_][A-Za-z0-9_]*``, all unique, none a prefix
    of another (importers that match bones by prefix confuse such names).
    """
    bad = [n for n in names if not NAME_PATTERN.match(n)]
    if bad:
        raise ValueError(f"invalid BVH joint names {bad[:5]!r}: use [A-Za-z_][A-Za-z0-9_]* (see sanitize_names)")
    srt = sorted(names)
    for a, b in zip(srt, srt[1:]):
        if a == b:
            raise ValueError(f"duplicate BVH joint name {a!r} (see sanitize_names)")
        if b.startswith(a):
            raise ValueError(f"BVH joint name {a!r} is a prefix of {b!r} (see sanitize_names)")


def _clashes(name: str, others: Sequence[str]) -> bool:
    return any(o.startswith(name) or name.startswith(o) for o in others)


def sanitize_names(names: Sequence[str]) -> list[str]:
    """Turn any list of strings into valid BVH joint names (see :func:`check_names`).

    Characters outside ``[A-Za-z0-9_]`` become ``_``; an empty name becomes
    ``joint``; a leading digit gets a ``_`` in front. Duplicates are all
    numbered (``A, A`` -> ``A_1, A_2``; zero-padded so the numbers are not
    prefixes of each other). A name that is a prefix of another gets a suffix
    (``Hip, Hips`` -> ``Hip_1, Hips``): the first of ``_1, _2, ...`` that
    clashes with no other name, else a single character that no other name
    continues it with. Names that are already valid and clash with nothing
    are kept.

    Parameters
    ----------
    names : sequence of str, length S

    Returns
    -------
    list of str, length S
    """
    out = []
    for n in names:
        n = re.sub(r"[^A-Za-z0-9_]", "_", str(n))
        if not n:
            n = "joint"
        if n[0].isdigit():
            n = "_" + n
        out.append(n)
    while True:
        srt = sorted(set(out))
        counts: dict[str, int] = {}
        for n in out:
            counts[n] = counts.get(n, 0) + 1
        # the shortest name that equals or prefixes another: no other name prefixes it
        bad = [a for a, b in zip(srt, srt[1:]) if b.startswith(a)] + [n for n, c in counts.items() if c > 1]
        if not bad:
            return out
        name = min(bad, key=lambda n: (len(n), n))
        where = [i for i, n in enumerate(out) if n == name]
        if len(where) > 1:
            width = len(str(len(where)))
            for k, i in enumerate(where, 1):
                out[i] = f"{name}_{k:0{width}d}"
            continue
        others = [n for n in out if n != name]
        for k in range(1, len(out) + 2):
            cand = f"{name}_{k}"
            if not _clashes(cand, others):
                break
        else:  # every "_k" is taken or prefixed by another name: one free next character
            used = {o[len(name)] for o in others if o.startswith(name) and len(o) > len(name)}
            free = [c for c in "_0123456789abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ" if c not in used]
            cand = name + (free[0] if free else "_")  # no free character: go one deeper next round
        out[where[0]] = cand


# --------------------------------------------------------------------------- writing


def _default_end_site(skel: BvhSkeleton, s: int, precision: int) -> np.ndarray:
    """End Site for leaf ``s`` when the given one is (as written) zero.

    Half the leaf's own bone further along it; for a leaf with a zero bone,
    a quarter of the median non-zero bone length along +Y; 10 units along +Y
    when the skeleton has no non-zero bone at all.
    """
    tiny = 10.0 ** (-precision)
    own = skel.offset[s] if s > 0 else np.zeros(3)
    if np.linalg.norm(own) > 10 * tiny:
        end = 0.5 * own
    else:
        lengths = np.linalg.norm(skel.offset[1:], axis=1)
        lengths = lengths[lengths > 10 * tiny]
        end = np.array([0.0, 0.25 * float(np.median(lengths)) if lengths.size else 10.0, 0.0])
    if np.abs(end).max() < 10 * tiny:
        end = np.array([0.0, 10.0, 0.0])
    return end


def _header(skel: BvhSkeleton, dfs: np.ndarray, n_frames: int, frame_time: float, precision: int) -> str:
    rot = " ".join(f"{c}rotation" for c in skel.order)
    fmt = f"{{:.{precision}f}}"

    def vec(v: np.ndarray) -> str:
        return " ".join(fmt.format(x + 0.0) for x in np.round(v, precision))

    leaf = skel.is_leaf
    depth = np.zeros(skel.n_joints, dtype=np.int64)
    for s in range(1, skel.n_joints):
        depth[s] = depth[skel.parent[s]] + 1
    lines = ["HIERARCHY"]
    open_: list[int] = []  # joints whose "}" is pending
    for s in dfs:
        while open_ and open_[-1] != skel.parent[s]:
            lines.append("\t" * depth[open_.pop()] + "}")
        ind = "\t" * depth[s]
        if s == 0:
            lines += [f"ROOT {skel.names[0]}", "{", f"\tOFFSET {vec(skel.offset[0])}",
                      f"\tCHANNELS 6 Xposition Yposition Zposition {rot}"]
        else:
            lines += [f"{ind}JOINT {skel.names[s]}", f"{ind}{{", f"{ind}\tOFFSET {vec(skel.offset[s])}",
                      f"{ind}\tCHANNELS 3 {rot}"]
        if leaf[s]:
            end = skel.end_site[s]
            if np.abs(np.round(end, precision)).max() == 0.0:
                end = _default_end_site(skel, s, precision)
            lines += [f"{ind}\tEnd Site", f"{ind}\t{{", f"{ind}\t\tOFFSET {vec(end)}", f"{ind}\t}}"]
        open_.append(s)
    while open_:
        lines.append("\t" * depth[open_.pop()] + "}")
    lines += ["MOTION", f"Frames: {n_frames}", f"Frame Time: {format_frame_time(frame_time)}"]
    return "\n".join(lines) + "\n"


#: Significant digits of ``Frame Time:``: 1/120 s is written 0.008333333333, which reads back
#: as 120.0000000048 fps (relative error below 1e-10; 8 decimals, 0.00833333, read back as
#: 120.000048 fps).
FRAME_TIME_DIGITS = 10


def format_frame_time(frame_time: float) -> str:
    """``Frame Time:``'s value: :data:`FRAME_TIME_DIGITS` significant digits, at least 8 decimals.

    ``1 / float(format_frame_time(1 / rate))`` is the rate within a relative
    5e-10 (half a unit in the tenth digit), so an importer that takes the rate
    as ``1 / Frame Time`` (Blender does) gets it to about 1e-10.
    """
    if not (math.isfinite(frame_time) and frame_time > 0):
        raise ValueError(f"frame_time must be positive and finite, got {frame_time!r}")
    decimals = max(8, FRAME_TIME_DIGITS - 1 - math.floor(math.log10(frame_time)))
    return f"{frame_time:.{decimals}f}"


def _transpose_blocks(flat: np.ndarray, take: np.ndarray | None = None, scale: np.ndarray | None = None) -> np.ndarray:
    """The (F, K) array ``flat`` (optionally ``flat[:, take] * scale``) transposed to a new (K, F) array.

    Copied a few hundred frames at a time, so that each block stays in the
    cache: about twice as fast as one transposing copy of a long take.
    """
    F = flat.shape[0]
    out = np.empty((flat.shape[1] if take is None else take.size, F))
    for f in range(0, F, _CACHE_FRAMES):
        blk = flat[f : f + _CACHE_FRAMES]
        if take is not None:
            blk = np.take(blk, take, axis=1)
        if scale is not None:
            blk = blk * scale
        out[:, f : f + _CACHE_FRAMES] = blk.T
    return out


def _frames_innermost(a: np.ndarray) -> np.ndarray:
    """``a`` (F, ...) stored with the frame axis innermost: every other index is a contiguous series over frames.

    The same logical array (a copy unless it is stored so already). The
    elementwise kernels of the writer (:func:`_rotation_error`,
    :func:`~mocapskel.solvers.rotations.matrix_to_euler` and
    :func:`~mocapskel.solvers.rotations.unwrap_euler`) read ``a[..., i, j]``
    or ``a[..., k]`` and run along frames: on this layout they stream
    contiguous memory instead of a 72- or 24-byte stride (2-3x faster).
    """
    a = np.asarray(a, dtype=np.float64)
    if a.ndim < 2 or a.shape[0] == 0 or np.moveaxis(a, 0, -1).flags.c_contiguous:
        return a
    F = a.shape[0]
    out = _transpose_blocks(np.ascontiguousarray(a).reshape(F, -1)).reshape(a.shape[1:] + (F,))
    return np.moveaxis(out, -1, 0)


def _prepare(
    skel: BvhSkeleton, root_pos: np.ndarray, local_rot: np.ndarray, frame_time: float, precision: int
) -> tuple[str, np.ndarray]:
    """Validate everything; return the header text and the (F, 3 + 3S) channel values."""
    check_names(skel.names)
    root_pos = np.asarray(root_pos, dtype=np.float64)
    local_rot = np.asarray(local_rot, dtype=np.float64)
    S = skel.n_joints
    if root_pos.ndim != 2 or root_pos.shape[1] != 3:
        raise ValueError(f"root_pos must be (F, 3), got {root_pos.shape}")
    F = root_pos.shape[0]
    if local_rot.shape != (F, S, 3, 3):
        raise ValueError(f"local_rot must be (F, S, 3, 3) = {(F, S, 3, 3)}, got {local_rot.shape}")
    if not (isinstance(precision, (int, np.integer)) and 1 <= precision <= 15):
        raise ValueError(f"precision must be an integer in 1..15, got {precision!r}")
    if not (np.isfinite(frame_time) and frame_time > 0):
        raise ValueError(f"frame_time must be positive, got {frame_time!r}")
    local_rot = _frames_innermost(local_rot)
    with np.errstate(over="ignore", invalid="ignore"):
        suspect = not np.isfinite(root_pos.sum() + local_rot.sum())  # NaN or inf somewhere, or huge values
    if suspect:
        bad = ~np.isfinite(root_pos).all(axis=1) | ~np.isfinite(local_rot).all(axis=(1, 2, 3))
        if bad.any():
            raise ValueError(
                f"NaN or inf in the motion ({int(bad.sum())} frames, first {int(np.flatnonzero(bad)[0])}): fill gaps before writing BVH"
            )
    err = _rotation_error(local_rot)
    if err > 1e-6:
        raise ValueError(f"local_rot must hold rotation matrices (error {err:.3g} from orthonormal, det +1)")
    dfs = depth_first_order(skel.parent)
    ang = unwrap_euler(_frames_innermost(matrix_to_euler(local_rot, skel.order)), skel.order)
    motion = np.empty((F, 3 + 3 * S))
    motion[:, :3] = root_pos
    motion[:, 3:].reshape(F, S, 3)[...] = ang if np.array_equal(dfs, np.arange(S)) else ang[:, dfs]
    return _header(skel, dfs, F, float(frame_time), precision), motion


def _rotation_error(R: np.ndarray) -> float:
    """Largest deviation of (F, ..., 3, 3) matrices from a rotation: max |R^T R - I| and |det - 1|.

    Written out entry by entry (numpy's batched 3x3 matmul and det are several
    times slower on a million matrices), a few thousand frames at a time so
    that the temporaries stay in the cache.
    """
    if R.size == 0:
        return 0.0
    return max(_rotation_error_block(R[f : f + _CHECK_FRAMES]) for f in range(0, R.shape[0], _CHECK_FRAMES))


def _rotation_error_block(R: np.ndarray) -> float:
    col = [R[..., :, a] for a in range(3)]
    err = 0.0
    for a in range(3):
        for b in range(a, 3):
            g = col[a][..., 0] * col[b][..., 0] + col[a][..., 1] * col[b][..., 1] + col[a][..., 2] * col[b][..., 2]
            err = max(err, float(np.abs(g - (a == b)).max()))
    c0, c1, c2 = col
    det = (
        c0[..., 0] * (c1[..., 1] * c2[..., 2] - c1[..., 2] * c2[..., 1])
        - c0[..., 1] * (c1[..., 0] * c2[..., 2] - c1[..., 2] * c2[..., 0])
        + c0[..., 2] * (c1[..., 0] * c2[..., 1] - c1[..., 1] * c2[..., 0])
    )
    return max(err, float(np.abs(det - 1.0).max()))


def _ascii_table(n_digits: int, leading_zeros: bool = True) -> np.ndarray:
    """``T[x]``: the ``n_digits`` ASCII digits of ``x`` packed in a 64-bit word, first digit in the lowest byte.

    Without ``leading_zeros`` the leading zeros are zero bytes (and 0 is all zero bytes).
    """
    x = np.arange(10**n_digits, dtype=np.uint64)
    out = np.zeros_like(x)
    for k in range(n_digits):
        power = np.uint64(10 ** (n_digits - 1 - k))
        char = x // power % np.uint64(10) + np.uint64(ord("0"))
        if not leading_zeros:
            char *= x >= power
        out |= char << np.uint64(8 * k)
    return out


_DIGITS3 = _ascii_table(3)
_DIGITS3_LEADING = _ascii_table(3, leading_zeros=False)


def _format_fixed(blk: np.ndarray, precision: int) -> bytes:
    """Rows of numbers as ``"%.{precision}f"`` ASCII text, space separated, one line per row.

    ``blk`` must be rounded to ``precision`` decimals already (and ``+ 0.0``, so
    no ``-0``). ``q = rint(|x| 10^p)`` holds exactly the digits printf prints.
    Precision 6 (the writer's default) with ``|x| < 10^7`` is packed 16 bytes
    per number by :func:`_format_p6`. Otherwise every number is written
    right-aligned into a column of a (width, N) byte grid, one vector operation
    per decimal digit. Either way the padding is zero bytes, dropped by one
    ``bytes.translate`` of the whole block. Numbers too large for exact
    integer arithmetic in float64 (``|x| 10^p >= 2^52``) go through ``%``
    instead.
    """
    n, C = blk.shape
    v = blk.ravel()
    q = np.rint(np.abs(v) * 10.0**precision)  # exact integers: the printed digits
    if v.size == 0 or q.max() >= 2.0**52:
        row = " ".join([f"%.{precision}f"] * C) + "\n"
        return ((row * n) % tuple(v.tolist())).encode("ascii")
    if precision == 6 and q.max() < 1e13:
        text = _format_p6(q, v < 0, C)
    else:
        n_digits = precision + 1
        while 10.0**n_digits <= q.max():
            n_digits += 1
        width = n_digits + 3  # separator, sign, digits, point
        grid = np.zeros((width, v.size), np.uint8)
        used = np.full(v.size, precision + 1)  # digits each number shows
        r = width - 1
        for i in range(n_digits):
            if i == precision:
                grid[r] = ord(".")
                r -= 1
            elif i > precision:
                used += q > 0
            high = np.floor(q / 10.0)
            grid[r] = (q - 10.0 * high).astype(np.uint8) + ord("0")
            q = high
            r -= 1
        grid[1] = ord("-")
        grid[0] = ord(" ")
        grid[0, ::C] = ord("\n")
        keep = np.arange(width)[:, None] >= (width - 1 - used)[None, :]
        keep[1] = v < 0
        keep[0] = True
        grid *= keep
        text = np.ascontiguousarray(grid.T).tobytes()
    return text.translate(None, b"\0")[1:] + b"\n"


def _format_p6(q: np.ndarray, negative: np.ndarray, n_columns: int) -> bytes:
    """Numbers ``q / 10^6`` (``q`` integer-valued, below 10^13) as 16-byte slots.

    Bytes of a slot: separator (a newline before the first number of a row),
    sign, the six integer digits above the units (leading zeros as zero
    bytes), the units digit, the point, the six decimals; a missing sign is a
    zero byte too. Each half is one little-endian 64-bit word put together
    from 3-digit lookups, so the slots need no byte transpose.
    """
    u64 = np.uint64
    qi = q.astype(u64)
    ip = qi // u64(1_000_000)
    fp = qi - ip * u64(1_000_000)
    fa = fp // u64(1000)
    hi = ip // u64(10)  # integer digits above the units, below 10^6
    hb = hi // u64(1000)
    hc = hi - hb * u64(1000)
    slots = np.empty((q.size, 2), dtype="<u8")
    tail = _DIGITS3[fp - fa * u64(1000)] << u64(40)
    tail |= _DIGITS3[fa] << u64(16)
    tail |= ip - hi * u64(10)
    tail |= u64(ord("0") | ord(".") << 8)
    slots[:, 1] = tail
    # below 1000 the low three digits have their leading zeros blanked, above only the high three
    head = np.where(hb > 0, _DIGITS3[hc], _DIGITS3_LEADING[hc]) << u64(40)
    head |= _DIGITS3_LEADING[hb] << u64(16)
    head |= negative.astype(u64) * u64(ord("-") << 8)
    sep = np.full(q.size, ord(" "), dtype=u64)
    sep[::n_columns] = ord("\n")
    head |= sep
    slots[:, 0] = head
    return slots.tobytes()


def _motion_blocks(motion: np.ndarray, precision: int) -> Iterator[bytes]:
    """The MOTION lines as ASCII, a thousand frames per chunk."""
    for start in range(0, motion.shape[0], _BLOCK_FRAMES):
        blk = np.round(motion[start : start + _BLOCK_FRAMES], precision) + 0.0  # no "-0.000000"
        yield _format_fixed(blk, precision)


def bvh_text(
    skel: BvhSkeleton, root_pos: np.ndarray, local_rot: np.ndarray, frame_time: float, precision: int = 6
) -> str:
    """The text :func:`write_bvh` writes, as one string (same arguments)."""
    header, motion = _prepare(skel, root_pos, local_rot, frame_time, precision)
    return header + b"".join(_motion_blocks(motion, precision)).decode("ascii")


def write_bvh(
    path: str | os.PathLike,
    skel: BvhSkeleton,
    root_pos: np.ndarray,
    local_rot: np.ndarray,
    frame_time: float,
    precision: int = 6,
) -> None:
    """Write a BVH file that importers take as it is (see the module docstring).

    Everything is validated before the file is touched; the file is written to
    a temporary file beside ``path`` and renamed onto it when complete, so a
    failure leaves ``path`` as it was. 60,000 frames of 16 joints take about
    0.4 s.

    Parameters
    ----------
    path : str or PathLike
        The output file.
    skel : BvhSkeleton
        Names must pass :func:`check_names`. A leaf whose End Site is zero at
        ``precision`` decimals gets a default one: half its own bone further
        along the bone; for a zero-length leaf bone a quarter of the median
        bone length along +Y (10 units along +Y if every bone is zero).
    root_pos : (F, 3) array_like
        Root position per frame (the root's position channels, absolute).
    local_rot : (F, S, 3, 3) array_like
        Rotation of each joint relative to its parent (root: to the world).
        Written as Euler angles in ``skel.order``, continuous in time.
    frame_time : float
        Seconds per frame (1 / rate).
    precision : int
        Decimals of every number (OFFSETs and channels).

    Raises
    ------
    ValueError
        Invalid names, shapes or frame time; NaN or inf anywhere in the motion
        (the caller fills gaps); matrices that are not rotations.
    OSError
        When the file cannot be written.
    """
    header, motion = _prepare(skel, root_pos, local_rot, frame_time, precision)
    with atomic_open(path, "wb") as f:
        f.write(header.encode("ascii"))
        for block in _motion_blocks(motion, precision):
            f.write(block)


# --------------------------------------------------------------------------- reading

_CHANNEL_RE = re.compile(r"([XYZ])(position|rotation)\Z", re.IGNORECASE)


class _Tokens:
    """The HIERARCHY section as (token, line number) pairs."""

    def __init__(self, lines: list[str], first_line: int, source: str):
        self.toks: list[tuple[str, int]] = [
            (t, first_line + i) for i, line in enumerate(lines) for t in line.split()
        ]
        self.pos = 0
        self.source = source

    def error(self, msg: str, line: int | None = None) -> InputError:
        if line is None:
            line = self.toks[min(self.pos, len(self.toks) - 1)][1] if self.toks else 1
        return InputError(f"malformed BVH at line {line}: {msg}", self.source)

    def next(self, what: str) -> tuple[str, int]:
        if self.pos >= len(self.toks):
            raise self.error(f"file ends where {what} was expected")
        tok = self.toks[self.pos]
        self.pos += 1
        return tok

    def expect(self, word: str) -> None:
        tok, line = self.next(repr(word))
        if tok != word:
            raise self.error(f"expected {word!r}, found {tok!r}", line)

    def numbers(self, n: int, what: str) -> np.ndarray:
        vals = []
        for _ in range(n):
            tok, line = self.next(what)
            try:
                vals.append(float(tok))
            except ValueError:
                raise self.error(f"{what} needs {n} numbers, found {tok!r}", line) from None
        out = np.array(vals)
        if not np.isfinite(out).all():
            raise self.error(f"{what} is not finite")
        return out

    def rest_of_line(self, line: int) -> list[str]:
        out = []
        while self.pos < len(self.toks) and self.toks[self.pos][1] == line and self.toks[self.pos][0] != "{":
            out.append(self.toks[self.pos][0])
            self.pos += 1
        return out


def _parse_hierarchy(tk: _Tokens) -> tuple[list[str], list[int], list[np.ndarray], list[list[str]], list[np.ndarray]]:
    names: list[str] = []
    parent: list[int] = []
    offset: list[np.ndarray | None] = []
    channels: list[list[str] | None] = []
    end_site: list[np.ndarray] = []
    tk.expect("HIERARCHY")
    stack: list[int] = []
    while True:
        tok, line = tk.next("a joint")
        if tok in ("ROOT", "JOINT"):
            if tok == "ROOT" and names:
                raise tk.error("a second ROOT: files with several skeletons are not supported", line)
            if tok == "JOINT" and not stack:
                raise tk.error("JOINT outside the ROOT", line)
            name = " ".join(tk.rest_of_line(line))
            if not name:
                raise tk.error(f"{tok} without a name", line)
            names.append(name)
            parent.append(stack[-1] if stack else -1)
            offset.append(None)
            channels.append(None)
            end_site.append(np.zeros(3))
            tk.expect("{")
            stack.append(len(names) - 1)
        elif not stack:
            raise tk.error(f"expected ROOT, found {tok!r}", line)
        elif tok == "OFFSET":
            offset[stack[-1]] = tk.numbers(3, "OFFSET")
        elif tok == "CHANNELS":
            n_tok, n_line = tk.next("the channel count")
            try:
                n = int(n_tok)
            except ValueError:
                raise tk.error(f"channel count must be an integer, found {n_tok!r}", n_line) from None
            if not 0 <= n <= 6:
                raise tk.error(f"a joint has 0 to 6 channels, not {n}", n_line)
            chans = []
            for _ in range(n):
                c, c_line = tk.next("a channel name")
                m = _CHANNEL_RE.match(c)
                if not m:
                    raise tk.error(f"unknown channel {c!r}", c_line)
                chans.append(m.group(1).upper() + m.group(2).lower())
            if len(set(chans)) != len(chans):
                raise tk.error(f"repeated channel in {' '.join(chans)}", n_line)
            channels[stack[-1]] = chans
        elif tok == "End":
            site, s_line = tk.next("'Site'")
            if site != "Site":
                raise tk.error(f"expected 'End Site', found 'End {site}'", s_line)
            tk.expect("{")
            tk.expect("OFFSET")
            end_site[stack[-1]] = tk.numbers(3, "End Site OFFSET")
            tk.expect("}")
        elif tok == "}":
            s = stack.pop()
            if offset[s] is None:
                raise tk.error(f"joint {names[s]!r} has no OFFSET", line)
            if channels[s] is None:
                channels[s] = []
            if not stack:
                break
        else:
            raise tk.error(f"unexpected {tok!r} in joint {names[stack[-1]]!r}", line)
    if tk.pos != len(tk.toks):
        tok, line = tk.toks[tk.pos]
        if tok == "ROOT":
            raise tk.error("a second ROOT: files with several skeletons are not supported", line)
        raise tk.error(f"unexpected {tok!r} after the ROOT's closing brace", line)
    return names, parent, offset, channels, end_site  # type: ignore[return-value]


def parse_bvh(text: str, source: str = "<bvh>") -> tuple[BvhSkeleton, np.ndarray, np.ndarray, float]:
    """Parse the text of a BVH file; see :func:`read_bvh` (``source`` names it in errors)."""
    lines = text.splitlines()
    k_motion = next((i for i, l in enumerate(lines) if l.split()[:1] == ["MOTION"]), None)
    if k_motion is None:
        raise InputError("not a BVH file: no MOTION section", source)
    tk = _Tokens(lines[:k_motion], 1, source)
    if not tk.toks or tk.toks[0][0] != "HIERARCHY":
        raise InputError("not a BVH file: it must start with HIERARCHY", source)
    names, parent, offset, channels, end_site = _parse_hierarchy(tk)
    S = len(names)

    # MOTION header
    rest = [(i + 1, l) for i, l in enumerate(lines[k_motion + 1 :], k_motion + 1) if l.strip()]
    m = re.fullmatch(r"\s*Frames:\s*(\d+)\s*", rest[0][1]) if rest else None
    if not m:
        line = rest[0][0] if rest else k_motion + 2
        raise InputError(f"malformed BVH at line {line}: expected 'Frames: <count>' after MOTION", source)
    F = int(m.group(1))
    m = re.fullmatch(r"\s*Frame\s+Time:\s*(\S+)\s*", rest[1][1]) if len(rest) > 1 else None
    try:
        frame_time = float(m.group(1)) if m else math.nan
    except ValueError:
        frame_time = math.nan
    if not (math.isfinite(frame_time) and frame_time > 0):
        line = rest[1][0] if len(rest) > 1 else rest[0][0] + 1
        raise InputError(f"malformed BVH at line {line}: expected 'Frame Time: <seconds>' (positive)", source)
    data = rest[2:]
    n_chan = sum(len(c) for c in channels)
    if len(data) != F:
        raise InputError(f"Frames: says {F} but the file has {len(data)} lines of motion", source)
    if F == 0 or n_chan == 0:
        values = np.zeros((F, n_chan))
    else:
        # np.loadtxt on the list of lines: 0.5 s for 60,000 x 51 values, against
        # 0.9 s for np.array(text.split(), float); it also checks the row lengths.
        try:
            values = np.loadtxt([l for _, l in data], dtype=np.float64, comments=None, ndmin=2)
        except ValueError:
            values = None
        if values is None or values.shape != (F, n_chan):
            for n, l in data:
                toks = l.split()
                if len(toks) != n_chan:
                    raise InputError(
                        f"malformed BVH at line {n}: {len(toks)} values where the CHANNELS declare {n_chan}", source
                    )
                if not all(_is_float(t) for t in toks):
                    raise InputError(f"malformed BVH at line {n}: a motion value is not a number", source)
            raise InputError("malformed BVH: unreadable MOTION section", source)  # pragma: no cover
    bad_rows = ~np.isfinite(values).all(axis=1)
    if bad_rows.any():
        bad = data[int(np.flatnonzero(bad_rows)[0])][0]
        raise InputError(f"malformed BVH at line {bad}: a motion value is not finite", source)

    # channels -> root position and local rotations
    local_rot = np.empty((F, S, 3, 3))
    offsets = np.array(offset, dtype=np.float64)
    root_pos = np.broadcast_to(offsets[0], (F, 3)).copy()
    col = 0
    for s, chans in enumerate(channels):
        pos = np.broadcast_to(offsets[s], (F, 3)).copy()
        moved = False
        rot_axes = ""
        rot_cols = []
        for c in chans:
            if c.endswith("position"):
                pos[:, "XYZ".index(c[0])] = values[:, col]
                moved = True
            else:
                rot_axes += c[0]
                rot_cols.append(col)
            col += 1
        # fewer than 3 rotation channels: the missing axes at zero angle
        ang = np.zeros((F, 3))
        ang[:, : len(rot_cols)] = values[:, rot_cols]
        local_rot[:, s] = euler_to_matrix(ang, rot_axes + "".join(a for a in "XYZ" if a not in rot_axes))
        if s == 0:
            root_pos = pos
        elif moved and F:
            scale = max(1.0, float(np.abs(pos).max()))
            if np.abs(pos - pos[0]).max() > 1e-6 * scale:
                raise InputError(
                    f"joint {names[s]!r} has translation channels that change over time; "
                    "only the root may move (mocapskel reads rigid skeletons)",
                    source,
                )
            offsets[s] = pos[0]
    rot_orders = ["".join(c[0] for c in ch if c.endswith("rotation")) for ch in channels]
    order = next((o for o in rot_orders if len(o) == 3), "ZXY")
    skel = BvhSkeleton(tuple(names), np.array(parent), offsets, np.array(end_site), order)
    return skel, root_pos, local_rot, frame_time


def _is_float(tok: str) -> bool:
    try:
        float(tok)
    except ValueError:
        return False
    return True


def read_bvh(path: str | os.PathLike) -> tuple[BvhSkeleton, np.ndarray, np.ndarray, float]:
    """Read a BVH file (any channel order per joint, 3- or 6-channel joints, End Sites).

    Joints come in file order (depth first; parents before children). A
    non-root joint's position channels, where a file has them, must be
    constant over time and become its OFFSET (a BVH position channel
    replaces the OFFSET).

    Parameters
    ----------
    path : str or PathLike

    Returns
    -------
    skel : BvhSkeleton
        ``order`` is the first 3-rotation joint's order (the root's, in files
        mocapskel writes); ``local_rot`` holds every joint's own order exactly.
    root_pos : (F, 3) ndarray
        The root's position channels (its OFFSET where it has none).
    local_rot : (F, S, 3, 3) ndarray
        Each joint's rotation relative to its parent.
    frame_time : float
        Seconds per frame.

    Raises
    ------
    InputError
        When the file cannot be read or is not a well-formed BVH file; the
        message names the file and the line.
    """
    from .paths import require_regular_file

    if os.path.exists(path):  # (a missing file: "cannot read" below)
        require_regular_file(path, "a .bvh file")
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            text = f.read()
    except OSError as e:
        raise InputError(f"cannot read ({e.strerror or e}) — check the file's permissions", str(path)) from None
    try:
        return parse_bvh(text, str(path))
    except InputError as e:
        msg = e.args[0]
        if " — " in msg:
            raise
        raise InputError(f"{msg} — give a well-formed BVH file (export it again)", e.path) from None


# --------------------------------------------------------------------------- kinematics


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
    local = np.copy(rot)  # order "K": the layout of rot
    tmp = np.empty(rot.shape[0])
    for s in np.flatnonzero(parent >= 0):
        G, P = rot[:, s], rot[:, parent[s]]
        for i in range(3):
            for j in range(3):
                out = local[:, s, i, j]
                np.multiply(P[:, 0, i], G[:, 0, j], out=out)
                out += np.multiply(P[:, 1, i], G[:, 1, j], out=tmp)
                out += np.multiply(P[:, 2, i], G[:, 2, j], out=tmp)
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


# --------------------------------------------------------------------------- coordinates


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


# --------------------------------------------------------------------------- rotation order


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
    from ..solvers.rotations import ORDERS

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
    from ..solvers.rotations import ORDERS

    R = np.asarray(local_rot, dtype=np.float64)
    lim = np.cos(np.radians(within_deg))  # |sin b| above this
    out = np.zeros(len(ORDERS), dtype=np.int64)
    for n, order in enumerate(ORDERS):
        i, _, k, _ = _parse_order(order)
        x = R[..., i, k]
        out[n] = int(np.count_nonzero(x > lim) + np.count_nonzero(x < -lim))
    return out


def choose_rotation_order(local_rot: np.ndarray, preferred: str = "ZXY", min_margin_deg: float = 30.0,
                          near_deg: float = 20.0) -> str:
    """One rotation order for every joint of a take, far from gimbal lock.

    ``preferred`` when every joint stays at least ``min_margin_deg`` from lock
    in it (the Euler angles then turn at most twice as fast as the rotation).
    Otherwise the order with the fewest joint-frames within ``near_deg`` of
    lock (:func:`near_lock_counts`: where spikes can appear), and among those
    the one whose closest joint stays farthest from lock, ``preferred`` first
    among equals. See :func:`gimbal_margin`.
    """
    from ..solvers.rotations import ORDERS

    pref = preferred.upper()
    _parse_order(pref)
    R = np.asarray(local_rot)
    if R.shape[0] == 0 or R.shape[1] == 0:
        return pref
    worst = gimbal_margin(R).min(axis=0)
    if worst[ORDERS.index(pref)] >= min_margin_deg:
        return pref
    near = near_lock_counts(R, near_deg)
    cands = [pref] + [o for o in ORDERS if o != pref]
    return min(cands, key=lambda o: (near[ORDERS.index(o)], -worst[ORDERS.index(o)]))
