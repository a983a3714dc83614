"""BVH: write files the way importers want them (read back by :mod:`mocapskel.io.bvh_read`; the skeleton they
hold, its kinematics and its axes: :mod:`mocapskel.solvers.bvh_pose`).

What :func:`write_bvh` writes (DESIGN, "BVH the way importers want it"):

- one ROOT with 6 channels, ``Xposition Yposition Zposition`` then the three
  rotations; every JOINT exactly 3 rotation channels; one rotation order
  everywhere (default ``Zrotation Xrotation Yrotation``);
- joints depth first, children in index order;
- names that match ``[A-Za-z_][A-Za-z0-9_]*``, unique, none a prefix of
  another (:func:`~mocapskel.model.tree.sanitize_names` makes any list so);
- every leaf with a non-zero End Site;
- ``Frames:`` the number of frames, ``Frame Time:`` with 10 significant digits
  (at least 8 decimals) so that ``1 / Frame Time`` is the rate (:func:`format_frame_time`);
- Euler angles continuous frame to frame (:func:`~mocapskel.solvers.rotations.unwrap_euler`);
- no NaN: missing frames must be filled by the caller;
- atomically: a temporary file beside the target, renamed when complete.

Conventions (shared by the writer, the reader and :func:`~mocapskel.solvers.bvh_pose.forward_kinematics`):
``local_rot[f, s]`` is joint ``s``'s rotation relative to its parent, the
product of its rotation channels in channel order (intrinsic, see
:mod:`mocapskel.solvers.rotations`); the root's position channels are its
absolute position and replace its OFFSET (Blender, bvhio and the common
parsers read them so; parsers that add the two agree when the root OFFSET is
zero). Joint ``s`` sits at ``pos[parent] + G[parent] @ offset[s]`` with
``G`` the global (accumulated) rotations.

Coordinates: mocapskel works in the lab frame in mm; :func:`~mocapskel.solvers.bvh_pose.lab_to_bvh` and
:func:`~mocapskel.solvers.bvh_pose.lab_rot_to_bvh` apply the ``--up``/``--units`` rules (up z: axes as in
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
from collections.abc import Iterator

import numpy as np

from ..model.tree import check_names, depth_first_order
from ..solvers.bvh_pose import BvhSkeleton, _transpose_blocks
from ..solvers.parallel import run_ahead, run_blocks
from ..solvers.rotations import matrix_to_euler, unwrap_euler
from .atomic import atomic_open

__all__ = [
    "bvh_text",
    "format_frame_time",
    "write_bvh",
]


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
_CHECK_FRAMES = 4096  # frames per block of the rotation check


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

    def angles(joints: slice) -> np.ndarray:
        # every joint's angles are its own (elementwise, unwrapped joint by joint): halves of the joints
        # run side by side
        return unwrap_euler(_frames_innermost(matrix_to_euler(local_rot[:, joints], skel.order)), skel.order)

    half = (S + 1) // 2
    parts = run_blocks(angles, [slice(0, half), slice(half, S)] if S > 1 else [slice(0, S)])
    ang = parts[0] if len(parts) == 1 else np.concatenate(parts, axis=1)
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
    return max(run_blocks(_rotation_error_block, [R[f : f + _CHECK_FRAMES] for f in range(0, R.shape[0], _CHECK_FRAMES)]))


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
    """The MOTION lines as ASCII, a thousand frames per chunk (formatted on threads, a few chunks ahead)."""

    def text(start: int) -> bytes:
        blk = np.round(motion[start : start + _BLOCK_FRAMES], precision) + 0.0  # no "-0.000000"
        return _format_fixed(blk, precision)

    return run_ahead(text, range(0, motion.shape[0], _BLOCK_FRAMES))


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


