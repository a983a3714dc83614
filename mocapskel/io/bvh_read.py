"""BVH: read any BVH file back (the conventions are those of :mod:`mocapskel.io.bvh`)."""
from __future__ import annotations

import math
import os
import re

import numpy as np

from ..errors import InputError
from ..solvers.bvh_pose import BvhSkeleton
from ..solvers.rotations import euler_to_matrix


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


_CHANNEL_RE = re.compile(r"([XYZ])(position|rotation)\Z", re.IGNORECASE)
