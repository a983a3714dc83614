"""A self-contained HTML report of a fit: plots, tables and an animated 3-D view.

:func:`build_html` turns the ``Motion`` artifact of a fit and its JSON report
(:func:`mocapskel.report.build_report`) into one HTML page that needs nothing
else: the plots are embedded as base64 PNG (drawn with matplotlib's Agg
renderer, without pyplot), the 3-D view is plain JavaScript on a ``<canvas>``
with its data embedded as JSON. The page loads nothing from the network.

Sections: the take's summary; warnings; the 3-D view (markers and skeleton,
play/pause, frame slider, drag to rotate); segmentation (the marker-distance-std
matrix ordered by segment with the clusters outlined, and the eigen-gap); the
segment graph with its joint costs and the chosen tree, and the joints table;
per-joint residual over time; per-segment IK residual over time with the gaps
shaded; the bone-length table.

matplotlib is an optional dependency (``pip install 'mocapskel[report]'``);
:func:`require_matplotlib` raises a :class:`~mocapskel.errors.UsageError`
(exit code 2) when it is missing. This module writes no files.
"""
from __future__ import annotations

import base64
import dataclasses
import html
import importlib
import io
import json
import math
from typing import Any

import numpy as np

from .artifacts import Markers, Motion, Segments, Topology, markers_of
from .errors import UsageError
from .evaluate import joint_positions

__all__ = [
    "MAX_VIEWER_FRAMES",
    "PALETTE",
    "build_html",
    "joint_residual_series",
    "require_matplotlib",
    "segment_residual_series",
    "viewer_data",
]

#: At most this many frames of the take go into the 3-D view (longer takes are decimated).
MAX_VIEWER_FRAMES = 2000
#: Positions in the 3-D view's data are integers in this unit (mm): 0.1 mm.
VIEWER_QUANTUM_MM = 0.1
#: Time series with more samples than this are binned before plotting (line: rms per bin, band: min to max).
MAX_PLOT_SAMPLES = 4000
#: Segment colours (matplotlib's tab20 order, dark shades first), shared by plots and the 3-D view.
PALETTE: tuple[str, ...] = (
    "#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f",
    "#bcbd22", "#17becf", "#aec7e8", "#ffbb78", "#98df8a", "#ff9896", "#c5b0d5", "#c49c94",
    "#f7b6d2", "#c7c7c7", "#dbdb8d", "#9edae5",
)
_LEFT_OUT_COLOUR = "#9a9a9a"
_DPI = 100


def require_matplotlib() -> None:
    """Check that matplotlib can be imported.

    Raises
    ------
    UsageError
        When it cannot (exit code 2), saying which extra to install.
    """
    try:
        importlib.import_module("matplotlib")
    except ImportError:
        raise UsageError(
            "the HTML report needs matplotlib, which is not installed — install mocapskel[report] "
            "(pip install 'mocapskel[report]')"
        ) from None


def colour(s: int) -> str:
    """The colour of segment ``s`` (grey for ``-1``: a marker on no segment)."""
    return _LEFT_OUT_COLOUR if s < 0 else PALETTE[s % len(PALETTE)]


# --------------------------------------------------------------------------- data


def _chain(motion: Motion) -> tuple[Markers | None, Segments | None, Topology | None]:
    """The markers, segments and topology a motion was computed from (None where it carries none)."""
    joints = motion.skeleton.joints
    topo = joints.topology if joints is not None else None
    segs = topo.segments if topo is not None else None
    try:
        mk = markers_of(motion)
    except (ValueError, AttributeError):
        mk = None
    return mk, segs, topo


def _rms_rows(x: np.ndarray) -> np.ndarray:
    """Per row of ``x`` (F, N), the rms over its finite entries; NaN for a row with none."""
    ok = np.isfinite(x)
    n = ok.sum(axis=1)
    ss = np.where(ok, x, 0.0) ** 2
    out = np.full(x.shape[0], np.nan)
    has = n > 0
    out[has] = np.sqrt(ss[has].sum(axis=1) / n[has])
    return out


def joint_residual_series(motion: Motion) -> np.ndarray:
    """Per frame and joint, how far the markers are from keeping their distance to the joint.

    For the joint between segments ``a`` and ``b`` (a tree edge) and every marker
    ``m`` of either segment, ``d[f, m] = |marker(f, m) - joint(f)|`` with the
    joint centre estimated by the joints stage; the series is, per frame, the rms
    over the markers seen of ``d[f, m] - mean_f d[f, m]``. A perfect joint on rigid
    segments gives zero. Its rms over frames is close to the joint's reported
    residual.

    Parameters
    ----------
    motion : Motion
        The IK artifact (it carries the joints, segments and markers).

    Returns
    -------
    (F, E) ndarray
        mm; NaN where the joint is not placed or none of its markers is seen.
        ``(F, 0)`` when the motion carries no joints.
    """
    F = motion.root_pos.shape[0]
    joints = motion.skeleton.joints
    mk, segs, topo = _chain(motion)
    if joints is None or segs is None or topo is None or mk is None:
        return np.zeros((F, 0))
    pts = mk.points
    out = np.full((F, topo.edges.shape[0]), np.nan)
    for e, (a, b) in enumerate(topo.edges.tolist()):
        idx = np.concatenate([segs.members(a), segs.members(b)])
        if idx.size == 0:
            continue
        d = np.linalg.norm(pts[:, idx] - joints.centres[:, e, None, :], axis=-1)  # (F, n), NaN where unseen
        ok = np.isfinite(d)
        cnt = ok.sum(axis=0)
        mean = np.where(cnt > 0, np.where(ok, d, 0.0).sum(axis=0) / np.maximum(cnt, 1), np.nan)
        out[:, e] = _rms_rows(d - mean)
    return out


def segment_residual_series(motion: Motion) -> tuple[np.ndarray, np.ndarray]:
    """Per frame and segment, the rms IK residual of the segment's markers, and where it has gaps.

    Parameters
    ----------
    motion : Motion
        The IK artifact.

    Returns
    -------
    rms : (F, S) ndarray
        mm; NaN where none of the segment's markers is seen.
    gap : (F, S) bool ndarray
        True where at least one of the segment's markers is not seen (the
        skeleton fills it in).
    """
    sk = motion.skeleton
    F, S = motion.rot.shape[:2]
    rms = np.full((F, S), np.nan)
    gap = np.zeros((F, S), dtype=bool)
    for s in range(S):
        idx = np.flatnonzero(sk.marker_segment == s)
        if idx.size == 0:
            continue
        r = motion.residual[:, idx]
        rms[:, s] = _rms_rows(r)
        gap[:, s] = ~np.isfinite(r).all(axis=1)
    return rms, gap


def _quantise(a: np.ndarray, origin: np.ndarray) -> list[list[int | None]]:
    """(n, K, 3) mm -> n flat lists of integers in units of 0.1 mm relative to ``origin``; None for NaN."""
    n = a.shape[0]
    q = np.round((a - origin) / VIEWER_QUANTUM_MM).reshape(n, -1)
    bad = ~np.isfinite(q)
    rows = np.where(bad, 0, q).astype(np.int64).tolist()
    for f, k in zip(*np.nonzero(bad)):
        rows[f][k] = None
    return rows


def viewer_data(motion: Motion, max_frames: int = MAX_VIEWER_FRAMES) -> dict[str, Any]:
    """The 3-D view's data: markers, joints and end sites per frame, decimated and rounded.

    Parameters
    ----------
    motion : Motion
        The IK artifact.
    max_frames : int
        At most this many frames are kept: every ``ceil(F / max_frames)``-th.

    Returns
    -------
    dict
        JSON-able: ``rate``, ``step`` (frames of the take per kept frame),
        ``frames`` (frames in the take), ``n`` (frames kept), ``quantum_mm``,
        ``origin`` (mm, subtracted from every position), ``up`` ("z": the lab
        frame's up axis), ``labels``, ``marker_segment``, ``names``, ``parent``,
        ``colours``, ``leaves`` (segments with an end site), and per kept frame
        the flat lists ``markers`` (3 M), ``joints`` (3 S) and ``ends``
        (3 per leaf) of integers in ``quantum_mm`` (None where not seen).
    """
    if max_frames < 1:
        raise ValueError(f"max_frames must be at least 1, got {max_frames}")
    sk = motion.skeleton
    F, S = motion.rot.shape[:2]
    step = max(1, math.ceil(F / max_frames))
    idx = np.arange(0, F, step)
    sub = dataclasses.replace(motion, root_pos=motion.root_pos[idx], rot=motion.rot[idx], residual=motion.residual[idx])
    jp = joint_positions(sub)  # (n, S, 3)
    leaves = [s for s in range(S) if np.linalg.norm(sk.end_site[s]) > 0]
    ends = (
        jp[:, leaves] + np.einsum("fsij,sj->fsi", sub.rot[:, leaves], sk.end_site[leaves])
        if leaves else np.zeros((idx.size, 0, 3))
    )
    mk, _, _ = _chain(motion)
    if mk is not None and mk.points.shape[0] == F and mk.n_markers == sk.marker_segment.size:
        pts = mk.points[idx]
        labels = list(mk.labels)
    else:  # a motion that carries no markers: show the skeleton alone
        pts = np.zeros((idx.size, 0, 3))
        labels = []
    allp = np.concatenate([jp.reshape(-1, 3), pts.reshape(-1, 3), ends.reshape(-1, 3)])
    allp = allp[np.isfinite(allp).all(axis=1)]
    origin = np.round(allp.mean(axis=0)) if allp.size else np.zeros(3)
    return {
        "rate": float(motion.rate) if motion.rate else 0.0,
        "step": int(step),
        "frames": int(F),
        "n": int(idx.size),
        "quantum_mm": VIEWER_QUANTUM_MM,
        "origin": [float(v) for v in origin],
        "up": "z",
        "labels": labels,
        "marker_segment": [int(s) for s in sk.marker_segment.tolist()][: len(labels)],
        "names": list(sk.names),
        "parent": [int(p) for p in sk.parent.tolist()],
        "colours": [colour(s) for s in range(S)],
        "leaves": leaves,
        "markers": _quantise(pts, origin),
        "joints": _quantise(jp, origin),
        "ends": _quantise(ends, origin),
    }


def _json_for_script(obj: Any) -> str:
    """JSON text that is safe inside ``<script type="application/json">`` ("<", ">", "&" escaped)."""
    text = json.dumps(obj, separators=(",", ":"), allow_nan=False)
    return text.replace("<", "\\u003c").replace(">", "\\u003e").replace("&", "\\u0026")


# --------------------------------------------------------------------------- plots


def _figure(width: float, height: float, constrained: bool = True) -> Any:
    """A matplotlib Figure on the Agg canvas (no pyplot: no global state, no GUI backend)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), dpi=_DPI, layout="constrained" if constrained else None)
    FigureCanvasAgg(fig)
    return fig


def _png(fig: Any, alt: str, cls: str = "") -> str:
    """An ``<img>`` element holding the figure as a base64 PNG."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=_DPI, metadata={"Software": None})
    data = base64.b64encode(buf.getvalue()).decode("ascii")
    return f'<img class="plot {cls}" alt="{html.escape(alt)}" src="data:image/png;base64,{data}">'


def _order_by_segment(group: np.ndarray) -> tuple[np.ndarray, list[tuple[int, int, int]]]:
    """Marker order grouped by segment (left-out markers last) and the blocks (segment, start, stop)."""
    order, blocks, start = [], [], 0
    for s in range(int(group.max()) + 1 if group.size else 0):
        m = np.flatnonzero(group == s)
        if m.size:
            order.extend(m.tolist())
            blocks.append((s, start, start + m.size))
            start += m.size
    order.extend(np.flatnonzero(group < 0).tolist())
    return np.array(order, dtype=int), blocks


def _plot_dist_std(segs: Segments, labels: tuple[str, ...], names: tuple[str, ...]) -> str:
    """The (M, M) distance-std matrix, markers ordered by segment, each segment's block outlined (log colour scale)."""
    from matplotlib.colors import LogNorm
    from matplotlib.patches import Rectangle

    order, blocks = _order_by_segment(segs.group)
    M = order.size
    d = np.asarray(segs.dist_std, dtype=float)[np.ix_(order, order)]
    off = d[~np.eye(M, dtype=bool)]
    pos = off[np.isfinite(off) & (off > 0)]
    lo = max(float(pos.min()), 1e-3) if pos.size else 1e-3
    hi = max(float(pos.max()), lo * 10) if pos.size else 1.0
    d = np.where(np.eye(M, dtype=bool) | ~np.isfinite(d), np.nan, np.clip(d, lo, hi))
    size = min(7.5, 3.2 + 0.085 * M)
    fig = _figure(size + 1.2, size)
    ax = fig.add_subplot()
    im = ax.imshow(d, cmap="viridis_r", norm=LogNorm(vmin=lo, vmax=hi), interpolation="nearest")
    for s, a, b in blocks:
        ax.add_patch(Rectangle((a - 0.5, a - 0.5), b - a, b - a, fill=False, edgecolor="#d62728", linewidth=1.6))
    fs = 6 if M <= 60 else (4 if M <= 120 else 0)
    if fs:
        ax.set_yticks(range(M), [labels[i] for i in order], fontsize=fs)
    else:
        ax.set_yticks([])
    ax.set_xticks([(a + b - 1) / 2 for _, a, b in blocks], [names[s] if s < len(names) else f"seg{s}" for s, _, _ in blocks],
                  rotation=90, fontsize=7)
    ax.set_title("std of marker-pair distances (mm), markers ordered by segment", fontsize=9)
    fig.colorbar(im, ax=ax, shrink=0.8, label="distance std (mm)")
    return _png(fig, "marker-distance standard deviation matrix ordered by segment", "dist")


def _plot_eigengap(segs: Segments) -> str:
    """The leading eigenvalues of the affinity and the gaps between them; the chosen count marked."""
    ev = np.asarray(segs.eigvals, dtype=float)
    ev = ev[np.isfinite(ev)]
    k = segs.n_segments
    K = int(min(ev.size, max(k + 10, 2 * k, 12)))
    ev = ev[:K]
    fig = _figure(5.2, 4.2)
    ax1, ax2 = fig.subplots(2, 1, sharex=True)
    x = np.arange(1, K + 1)
    ax1.plot(x, ev, "o-", color="#1f77b4", markersize=3.5)
    ax1.set_ylabel("eigenvalue")
    ax1.set_title("eigenvalues of the normalised affinity (largest first)", fontsize=9)
    gaps = ev[:-1] - ev[1:] if K > 1 else np.zeros(0)
    cols = ["#d62728" if i + 1 == k else "#9ab" for i in range(gaps.size)]
    ax2.bar(x[:-1] + 0.5, gaps, width=0.8, color=cols)
    ax2.set_ylabel("gap λk − λk+1")
    ax2.set_xlabel("k")
    if 1 <= k < K and ev.size:
        for ax in (ax1, ax2):
            ax.axvline(k + 0.5, color="#d62728", linestyle="--", linewidth=1)
        ax1.annotate(f"{k} segments", (k + 0.5, ev.min() + 0.5 * (ev.max() - ev.min())), xytext=(5, 0),
                     textcoords="offset points", color="#d62728", fontsize=8)
    return _png(fig, "eigenvalues and eigen-gaps", "eig")


def _plot_graph(topo: Topology, names: tuple[str, ...], n_alternatives: int = 1) -> str:
    """The segment graph: tree edges bold with their joint costs, each segment's cheapest other pairs dashed.

    Nodes are placed by networkx (Kamada-Kawai for the tree, which starts from a
    circle and is deterministic; seeded spring layout otherwise).
    """
    import networkx as nx

    S = topo.pair_cost.shape[0]
    tree = nx.Graph()
    tree.add_nodes_from(range(S))
    tree.add_edges_from((int(a), int(b)) for a, b in topo.edges)
    if S == 1:
        pos = {0: np.zeros(2)}
    elif nx.is_connected(tree):  # a tree: Kamada-Kawai spreads its branches out (deterministic start: a circle)
        pos = nx.kamada_kawai_layout(tree)
    else:
        pos = nx.spring_layout(tree, seed=7, iterations=300)
    pc = np.asarray(topo.pair_cost, dtype=float)
    in_tree = {frozenset((int(a), int(b))) for a, b in topo.edges}
    alt: set[frozenset[int]] = set()
    for s in range(S):
        row = [(pc[s, t], t) for t in range(S) if t != s and np.isfinite(pc[s, t]) and frozenset((s, t)) not in in_tree]
        alt.update(frozenset((s, t)) for _, t in sorted(row)[:n_alternatives])
    fig = _figure(9.0, 6.6)
    ax = fig.add_subplot()
    for e in sorted(alt, key=sorted):
        a, b = sorted(e)
        (xa, ya), (xb, yb) = pos[a], pos[b]
        ax.plot([xa, xb], [ya, yb], color="#aaaaaa", linewidth=0.8, linestyle="--", zorder=1)
        ax.text((xa + xb) / 2, (ya + yb) / 2, f"{pc[a, b]:.3g}", fontsize=6.5, color="#777777", ha="center", va="center", zorder=2,
                bbox={"boxstyle": "round,pad=0.1", "facecolor": "white", "edgecolor": "none", "alpha": 0.8})
    for (a, b), c in zip(topo.edges.tolist(), np.asarray(topo.cost, dtype=float).tolist()):
        (xa, ya), (xb, yb) = pos[a], pos[b]
        ax.plot([xa, xb], [ya, yb], color="#222222", linewidth=3.2, zorder=3)
        ax.text((xa + xb) / 2, (ya + yb) / 2, f"{c:.3g}" if math.isfinite(c) else "n/a", fontsize=7.5, ha="center",
                va="center", zorder=4, bbox={"boxstyle": "round,pad=0.15", "facecolor": "white", "edgecolor": "#222222", "linewidth": 0.6})
    for s in range(S):
        x, y = pos[s]
        root = s == topo.root
        ax.scatter([x], [y], s=820 if root else 640, color=colour(s), edgecolors="black", linewidths=2.5 if root else 0.8, zorder=5)
        ax.text(x, y, names[s] if s < len(names) else f"seg{s}", fontsize=7, ha="center", va="center", zorder=6,
                fontweight="bold" if root else "normal")
    ax.set_title("segment graph: the chosen tree (bold) and each segment's cheapest other pair (dashed); "
                 "joint costs in mm²; thick ring: the root", fontsize=8.5)
    ax.set_axis_off()
    ax.margins(0.08)
    return _png(fig, "segment graph with joint costs and the chosen tree")


def _reduce(
    t: np.ndarray, y: np.ndarray, mask: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None, np.ndarray | None]:
    """Bin long series so that plots stay light: per bin the rms, the minimum and the maximum.

    Returns ``(t, y, lo, hi, mask)``; ``lo`` and ``hi`` are None when the series
    is short enough to plot as it is. A bin's mask is set when any of its frames is.
    """
    F = t.size
    if F <= MAX_PLOT_SAMPLES:
        return t, y, None, None, mask
    b = math.ceil(F / MAX_PLOT_SAMPLES)
    nb = math.ceil(F / b)
    pad = nb * b - F

    def fold(a: np.ndarray, fill: Any) -> np.ndarray:
        return np.concatenate([a, np.full((pad,) + a.shape[1:], fill, dtype=a.dtype)]).reshape((nb, b) + a.shape[1:])

    yb = fold(y, np.nan)
    ok = np.isfinite(yb)
    n = ok.sum(axis=1)
    rms = np.full(nb, np.nan)
    rms[n > 0] = np.sqrt((np.where(ok, yb, 0.0) ** 2).sum(axis=1)[n > 0] / n[n > 0])
    lo = np.fmin.reduce(yb, axis=1)
    hi = np.fmax.reduce(yb, axis=1)
    mr = fold(mask, False).any(axis=1) if mask is not None else None
    return t[::b], rms, lo, hi, mr


def _grid(n: int) -> tuple[int, int]:
    """Rows and columns of small multiples for ``n`` panels."""
    ncols = 1 if n <= 1 else (2 if n <= 4 else 3)
    return math.ceil(n / ncols), ncols


def _plot_series(
    t: np.ndarray, y: np.ndarray, titles: list[str], colours: list[str], title: str, alt: str,
    level: list[float | None] | None = None, gap: np.ndarray | None = None,
) -> str:
    """Small multiples of time series ``y`` (F, n): one panel each, optional level lines and shaded gaps (F, n)."""
    n = y.shape[1]
    nrows, ncols = _grid(n)
    head = 0.62 if t.size <= MAX_PLOT_SAMPLES else 0.8  # room for the title's second line
    height = 0.38 + head + 1.5 * nrows
    fig = _figure(11.0, height, constrained=False)  # a fixed layout: constrained layout is slow with many panels
    fig.subplots_adjust(left=0.05, right=0.99, bottom=0.45 / height, top=1 - head / height, hspace=0.45, wspace=0.14)
    axes = np.atleast_1d(fig.subplots(nrows, ncols, sharex=True, squeeze=False)).ravel()
    binned = False
    for i, ax in enumerate(axes):
        if i >= n:
            ax.set_visible(False)
            continue
        tt, yy, lo, hi, gg = _reduce(t, y[:, i], gap[:, i] if gap is not None else None)
        if gg is not None and gg.any():
            ax.fill_between(tt, 0, 1, where=gg, transform=ax.get_xaxis_transform(), color="#f4a582", alpha=0.45,
                            linewidth=0, step="mid", label="gap")
        if lo is not None and hi is not None:
            binned = True
            ax.fill_between(tt, lo, hi, color=colours[i], alpha=0.3, linewidth=0, step="mid")
        ax.plot(tt, yy, color=colours[i], linewidth=0.8)
        if level is not None and level[i] is not None and math.isfinite(level[i]):
            ax.axhline(level[i], color="#555555", linewidth=0.7, linestyle=":")
        ax.set_title(titles[i], fontsize=8)
        ax.tick_params(labelsize=7)
        if i % ncols == 0:
            ax.set_ylabel("mm", fontsize=7)
        if i >= n - ncols:
            ax.set_xlabel("time (s)", fontsize=7)
        ax.set_ylim(bottom=0)
        ax.set_xlim(t[0], t[-1] if t[-1] > t[0] else t[0] + 1)
    if binned:
        title += f"\nlong take: the line is the rms over bins of {math.ceil(t.size / MAX_PLOT_SAMPLES)} frames, the band their minimum to maximum"
    fig.suptitle(title, fontsize=9)
    return _png(fig, alt)


# --------------------------------------------------------------------------- HTML


def _fmt(v: Any, digits: int = 3) -> str:
    """A table cell: numbers to ``digits`` significant figures, None as an em dash."""
    if v is None:
        return "—"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        if not math.isfinite(v):
            return "—"
        return f"{v:.{digits}g}" if abs(v) < 10 ** digits else f"{v:.0f}"
    if isinstance(v, (list, tuple)):
        return html.escape(", ".join(str(x) for x in v)) if v else "—"
    return html.escape(str(v))


def _table(header: list[str], rows: list[list[str]], cls: str = "") -> str:
    head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{c}</td>" for c in r) + "</tr>" for r in rows)
    return f'<table class="{cls}"><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>'


def _kv(rows: list[tuple[str, str]]) -> str:
    return '<table class="kv">' + "".join(f"<tr><th>{html.escape(k)}</th><td>{v}</td></tr>" for k, v in rows) + "</table>"


def _summary(report: dict, motion: Motion) -> str:
    inp = report.get("input", {})
    clean = report.get("clean", {}) or {}
    merge = report.get("merge_ids", {}) or {}
    ik = report.get("ik", {}) or {}
    params = report.get("params", {}) or {}
    rate = inp.get("rate_hz") or motion.rate
    frames = inp.get("frames", motion.root_pos.shape[0])
    dur = f"{frames / rate:.2f} s" if rate else "—"
    vis = inp.get("visible_fraction")
    filled = ik.get("filled_fraction")
    rows = [
        ("file", _fmt(inp.get("file") or motion.source)),
        ("frames", f"{_fmt(frames)} at {_fmt(rate)} Hz ({dur})"),
        ("markers", f"{_fmt(inp.get('markers'))} labels, {_fmt(merge.get('physical_markers'))} physical"
                    + (f", merged: {_fmt(len(merge.get('merged') or {}))}" if merge.get("merged") else "")),
        ("source units", _fmt(inp.get("source_units"))),
        ("visible", f"{100 * vis:.1f} % of marker samples" if vis is not None else "—"),
        ("cleaning", "{} jump samples, {} trimmed samples, {} short runs ({} samples), dropped: {}".format(
            _fmt(clean.get("jump_samples")), _fmt(clean.get("trimmed_samples")), _fmt(clean.get("short_runs")),
            _fmt(clean.get("short_run_samples")), _fmt(clean.get("dropped_markers") or "none"))),
        ("segments", f"{len(report.get('segments', []))}"
                     + (f" (markers left out: {_fmt(report.get('segments_left_out'))})" if report.get("segments_left_out") else "")
                     + "".join(f"; a group that did not move as one body ({_fmt(d.get('rigid_rms_mm'))} mm rigid-fit rms) split into "
                               + " | ".join(_fmt(" ".join(map(str, part))) for part in d.get("parts", []))
                               for d in report.get("segments_split") or [])),
        ("joints", f"{len(report.get('joints', []))}, root {_fmt((report.get('topology') or {}).get('root'))}"),
        ("rest frame", _fmt(report.get("rest_frame"))),
        ("IK marker rms", f"{_fmt(ik.get('marker_rms_mm'))} mm"),
        ("filled by the skeleton", f"{100 * filled:.1f} % of marker samples" if filled is not None else "—"),
        ("out of view", ", ".join(f"{html.escape(str(k))} {int(v)} frames ({100 * int(v) / frames:.0f} %)"
                                  for k, v in (ik.get("out_of_view_frames") or {}).items()) + " (no marker of the segment or below"
                        " it seen while others are: its joints keep the angles of the frames around, its motion there is made up)"
                        if ik.get("out_of_view_frames") and frames else "none"),
        ("parameters", _fmt(", ".join(f"{st}: " + " ".join(f"{k}={v}" for k, v in p.items())
                                      for st, p in params.items() if isinstance(p, dict)) or None)),
        ("time", ", ".join(f"{html.escape(str(k))} {float(v):.2f} s" for k, v in (report.get("seconds") or {}).items()) or "—"),
        ("cached stages", _fmt(report.get("cached_stages") or "none")),
        ("tool", _fmt(" ".join(str(v) for v in (report.get("tool") or {}).values()))),
    ]
    return _kv(rows)


def _joints_table(report: dict) -> str:
    costs = {(e.get("parent"), e.get("child")): e.get("joint_cost_mm2") for e in (report.get("topology") or {}).get("edges", [])}
    rows = []
    for j in report.get("joints", []):
        why = j.get("why", "")
        if j.get("note"):
            why = f"{why} ({j['note']})" if why else j["note"]
        rows.append([
            _fmt(j.get("parent")), _fmt(j.get("child")), _fmt(j.get("method")),
            _fmt(costs.get((j.get("parent"), j.get("child")))), _fmt(j.get("residual_mm")), _fmt(why or None),
        ])
    return _table(["parent", "child", "method", "joint cost (mm²)", "residual (mm)", "why"], rows)


def _bones_table(report: dict, motion: Motion) -> str:
    per_seg = (report.get("ik") or {}).get("marker_rms_mm_per_segment", {}) or {}
    count = np.bincount(motion.skeleton.marker_segment[motion.skeleton.marker_segment >= 0],
                        minlength=len(motion.skeleton.names))
    rows = []
    for s, b in enumerate(report.get("bones", [])):
        name = b.get("segment")
        sw = f'<span class="chip" style="background:{colour(s)}"></span>'
        rows.append([
            sw + _fmt(name), _fmt(b.get("parent")), _fmt(int(count[s]) if s < count.size else None),
            _fmt(b.get("length_mm"), 4), _fmt(b.get("rigid_fit_rms_mm")), _fmt(per_seg.get(name)),
        ])
    return _table(["segment", "parent", "markers", "bone length (mm)", "rigid fit rms (mm)", "IK rms (mm)"], rows, "num")


def _warnings(report: dict) -> str:
    ws = report.get("warnings") or []
    if not ws:
        return '<p class="ok">No warnings.</p>'
    return '<ul class="warnings">' + "".join(f"<li>{html.escape(str(w))}</li>" for w in ws) + "</ul>"


def build_html(motion: Motion, report: dict, *, max_frames: int = MAX_VIEWER_FRAMES, title: str | None = None) -> str:
    """The whole report as one self-contained HTML page.

    Parameters
    ----------
    motion : Motion
        The IK artifact of the fit (it carries the skeleton, joints, topology,
        segments and markers it was computed from).
    report : dict
        The JSON report of the same fit (:func:`mocapskel.report.build_report`).
    max_frames : int
        At most this many frames of the take go into the 3-D view.
    title : str, optional
        The page title; by default "mocapskel report — <input file>".

    Returns
    -------
    str
        The HTML text (UTF-8). Images are base64 PNG, the 3-D view is inline
        JavaScript with its data as inline JSON: nothing is loaded from elsewhere.

    Raises
    ------
    UsageError
        When matplotlib is not installed.
    """
    require_matplotlib()
    sk = motion.skeleton
    names = tuple(sk.names)
    mk, segs, topo = _chain(motion)
    src = (report.get("input") or {}).get("file") or motion.source or "take"
    title = title or f"mocapskel report — {src}"
    F, S = motion.rot.shape[:2]
    rate = float(motion.rate) if motion.rate else 0.0
    t = np.arange(F) / rate if rate > 0 else np.arange(F, dtype=float)

    sections: list[tuple[str, str, str]] = []  # (id, heading, body)
    sections.append(("summary", "Summary", _summary(report, motion)))
    n_w = len(report.get("warnings") or [])
    sections.append(("warnings", f"Warnings ({n_w})", _warnings(report)))

    data = viewer_data(motion, max_frames=max_frames)
    legend = "".join(f'<span class="legend"><span class="chip" style="background:{colour(s)}"></span>{html.escape(n)}</span>'
                     for s, n in enumerate(names))
    decim = (f"1 frame in {data['step']} of the take's {data['frames']} shown" if data["step"] > 1
             else f"all {data['frames']} frames shown")
    sections.append(("view", "3-D view", _VIEWER_HTML.format(
        legend=legend, decim=html.escape(decim), n_max=data["n"] - 1,
        data=_json_for_script(data), script=_VIEWER_JS)))

    if segs is not None and mk is not None:
        seg_body = (
            '<div class="row">' + _plot_dist_std(segs, mk.labels, names) + _plot_eigengap(segs) + "</div>"
            + '<p class="note">Left: the standard deviation of every marker-pair distance over the chosen sampling, '
              "markers ordered by segment; red squares outline the segments found (low std = same rigid body). "
              "Right: eigenvalues of the normalised affinity; the number of segments is where the largest gap is "
              "(unless given with --segments).</p>"
        )
    else:
        seg_body = '<p class="note">This artifact carries no segmentation.</p>'
    sections.append(("segments", "Segmentation", seg_body))

    if topo is not None:
        topo_body = _plot_graph(topo, names) + _joints_table(report)
    else:
        topo_body = '<p class="note">This artifact carries no topology.</p>'
    sections.append(("topology", "Segment graph and joints", topo_body))

    jr = joint_residual_series(motion)
    if jr.shape[1]:
        edges = topo.edges.tolist() if topo is not None else []
        jt = [f"{names[a]}–{names[b]}  ({sk.joints.method[e]}, {_fmt(float(sk.joints.residual[e]))} mm)"
              for e, (a, b) in enumerate(edges)]
        level = [float(v) for v in sk.joints.residual]
        body = _plot_series(t, jr, jt, [colour(b) for _, b in edges],
                            "joint residual: per frame, rms over the joint's markers of |distance to the joint − its mean| "
                            "(dotted: the joint's overall residual)", "per-joint residual over time", level=level)
    else:
        body = '<p class="note">This artifact carries no joint centres.</p>'
    sections.append(("joint-residual", "Joint residual over time", body))

    sr, gap = segment_residual_series(motion)
    per_seg = (report.get("ik") or {}).get("marker_rms_mm_per_segment", {}) or {}
    body = _plot_series(t, sr, [f"{n}  (rms {_fmt(per_seg.get(n))} mm)" for n in names], [colour(s) for s in range(S)],
                        "IK residual: per frame, rms distance of the segment's markers from the skeleton's; "
                        "shaded: a marker of the segment is missing (gap filled by the skeleton)",
                        "per-segment IK residual over time", gap=gap)
    sections.append(("ik-residual", "IK residual over time", body))
    sections.append(("bones", "Bones", _bones_table(report, motion)))

    nav = " · ".join(f'<a href="#{sid}">{html.escape(h)}</a>' for sid, h, _ in sections)
    body = "\n".join(f'<section id="{sid}"><h2>{html.escape(h)}</h2>\n{b}\n</section>' for sid, h, b in sections)
    return _PAGE.format(title=html.escape(title), nav=nav, body=body, css=_CSS)


# --------------------------------------------------------------------------- page template

_CSS = """
body{font:14px/1.45 system-ui,-apple-system,"Segoe UI",Roboto,Helvetica,Arial,sans-serif;margin:0;color:#222;background:#fafafa}
header{background:#263238;color:#fff;padding:10px 24px}header h1{font-size:20px;margin:4px 0}
nav{font-size:13px}nav a{color:#cfe3ff;text-decoration:none}
main{padding:8px 24px 40px;max-width:1240px}
section{background:#fff;border:1px solid #e3e3e3;border-radius:6px;padding:8px 16px 14px;margin:14px 0}
h2{font-size:17px;margin:6px 0 10px}
table{border-collapse:collapse;font-size:13px;margin:8px 0}
th,td{border-bottom:1px solid #e6e6e6;padding:3px 10px;text-align:left;vertical-align:top}
thead th{background:#f0f3f5}table.kv th{color:#555;font-weight:600;white-space:nowrap}
table.num td:nth-child(n+3){text-align:right;font-variant-numeric:tabular-nums}
img.plot{max-width:100%;height:auto;display:block;margin:6px 0}
.row{display:flex;flex-wrap:wrap;gap:1%;align-items:flex-start}.row img.dist{width:58%}.row img.eig{width:40%}
@media (max-width:900px){.row img.dist,.row img.eig{width:100%}}
.note{color:#555;font-size:12.5px}.ok{color:#2e7d32}
ul.warnings li{color:#b00020}
.chip{display:inline-block;width:11px;height:11px;border-radius:2px;margin-right:5px;vertical-align:-1px}
.legend{display:inline-block;margin:2px 10px 2px 0;font-size:12px}
#viewer{width:100%;max-width:960px;height:auto;background:#fff;border:1px solid #ddd;cursor:grab;display:block}
.controls{display:flex;flex-wrap:wrap;align-items:center;gap:10px;margin:6px 0;max-width:960px}
.controls input[type=range]{flex:1;min-width:200px}
.controls button{min-width:70px}
#viewer-label{font-variant-numeric:tabular-nums;font-size:13px;min-width:190px}
"""

_PAGE = """<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<meta name="generator" content="mocapskel">
<title>{title}</title>
<style>{css}</style>
</head>
<body>
<header><h1>{title}</h1><nav>{nav}</nav></header>
<main>
{body}
</main>
</body>
</html>
"""

_VIEWER_HTML = """<div class="controls">
<button type="button" id="viewer-play">Play</button>
<input type="range" id="viewer-slider" min="0" max="{n_max}" value="0" step="1" aria-label="frame">
<span id="viewer-label">frame 0</span>
</div>
<div class="controls">
<label><input type="checkbox" id="viewer-markers" checked> markers</label>
<label><input type="checkbox" id="viewer-skeleton" checked> skeleton</label>
<label><input type="checkbox" id="viewer-follow" checked> follow the subject</label>
<label>up axis <select id="viewer-up"><option value="z">Z</option><option value="y">Y</option></select></label>
<span class="note">drag to rotate, wheel to zoom, double-click to reset; space plays/pauses; {decim}</span>
</div>
<canvas id="viewer" width="960" height="600" aria-label="3-D view of the markers and the skeleton"></canvas>
<div>{legend}<span class="legend"><span class="chip" style="background:#222"></span>bones, joints (white)</span></div>
<div id="viewer-status" data-ok="0" data-points="0" data-lines="0" data-frame="-1" data-images="-1" data-error=""></div>
<noscript><p class="note">The 3-D view needs JavaScript.</p></noscript>
<script type="application/json" id="viewer-data">{data}</script>
<script>{script}</script>"""

_VIEWER_JS = r"""
(function () {
  "use strict";
  var status = document.getElementById("viewer-status");
  window.addEventListener("error", function (ev) {
    status.setAttribute("data-error", String((ev && ev.message) || "script error"));
  });
  window.addEventListener("load", function () {
    var imgs = document.querySelectorAll("img.plot"), ok = 0;
    for (var i = 0; i < imgs.length; i++) { if (imgs[i].complete && imgs[i].naturalWidth > 0) { ok++; } }
    status.setAttribute("data-images", ok + "/" + imgs.length);
  });
  var D = JSON.parse(document.getElementById("viewer-data").textContent);
  var canvas = document.getElementById("viewer");
  var ctx = canvas.getContext("2d");
  var slider = document.getElementById("viewer-slider");
  var playBtn = document.getElementById("viewer-play");
  var label = document.getElementById("viewer-label");
  var showMarkers = document.getElementById("viewer-markers");
  var showSkeleton = document.getElementById("viewer-skeleton");
  var upSelect = document.getElementById("viewer-up");
  var follow = document.getElementById("viewer-follow");
  var q = D.quantum_mm, n = D.n, S = D.names.length, M = D.labels.length;
  var view = { yaw: -0.7, pitch: 0.3, zoom: 1.0 };
  var frame = 0, playing = false, t0 = 0, f0 = 0;
  upSelect.value = D.up;

  // lab (x, y, z) -> (right, forward, up) for the chosen up axis
  function axes(x, y, z) { return upSelect.value === "y" ? [x, -z, y] : [x, y, z]; }

  // extent over all frames (lo, hi), each frame's centre (mean of its joints) and the
  // largest distance of anything drawn from its frame's centre (rad), in (right, forward, up)
  var lo, hi, centre, rad;
  function extent() {
    lo = [Infinity, Infinity, Infinity]; hi = [-Infinity, -Infinity, -Infinity];
    centre = []; rad = 0;
    var f, k, c, p, r;
    for (f = 0; f < n; f++) {
      var sum = [0, 0, 0], cnt = 0;
      r = D.joints[f];
      for (k = 0; k + 2 < r.length; k += 3) {
        if (r[k] === null || r[k + 1] === null || r[k + 2] === null) { continue; }
        p = axes(r[k] * q, r[k + 1] * q, r[k + 2] * q);
        sum[0] += p[0]; sum[1] += p[1]; sum[2] += p[2]; cnt++;
      }
      centre.push(cnt ? [sum[0] / cnt, sum[1] / cnt, sum[2] / cnt] : null);
    }
    var rows = [D.joints, D.markers, D.ends];
    for (var j = 0; j < rows.length; j++) {
      for (f = 0; f < n; f++) {
        r = rows[j][f];
        for (k = 0; k + 2 < r.length; k += 3) {
          if (r[k] === null || r[k + 1] === null || r[k + 2] === null) { continue; }
          p = axes(r[k] * q, r[k + 1] * q, r[k + 2] * q);
          for (c = 0; c < 3; c++) { if (p[c] < lo[c]) { lo[c] = p[c]; } if (p[c] > hi[c]) { hi[c] = p[c]; } }
          if (centre[f]) {
            var d = Math.sqrt(Math.pow(p[0] - centre[f][0], 2) + Math.pow(p[1] - centre[f][1], 2) + Math.pow(p[2] - centre[f][2], 2));
            if (d > rad) { rad = d; }
          }
        }
      }
    }
    for (c = 0; c < 3; c++) { if (!isFinite(lo[c])) { lo[c] = -500; hi[c] = 500; } }
    if (!(rad > 0)) { rad = 500; }
    // frames without joints keep the last known centre
    var last = [(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, (lo[2] + hi[2]) / 2];
    for (f = 0; f < n; f++) { if (centre[f]) { last = centre[f]; } else { centre[f] = last; } }
  }
  extent();

  // the point the view is centred on, and the radius that fits the canvas
  function focus() {
    if (follow.checked && n > 0) {
      return [[centre[frame][0], centre[frame][1], (lo[2] + hi[2]) / 2], Math.max(rad, (hi[2] - lo[2]) / 2)];
    }
    var r = 0.5 * Math.sqrt(Math.pow(hi[0] - lo[0], 2) + Math.pow(hi[1] - lo[1], 2) + Math.pow(hi[2] - lo[2], 2));
    return [[(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, (lo[2] + hi[2]) / 2], r || 1];
  }
  var F0 = [0, 0, 0], R0 = 1;
  function project(p, W, H) {
    var s = 0.48 * Math.min(W, H) / R0 * view.zoom;
    var a = p[0] - F0[0], b = p[1] - F0[1], h = p[2] - F0[2];
    var cyw = Math.cos(view.yaw), syw = Math.sin(view.yaw);
    var a2 = a * cyw - b * syw, b2 = a * syw + b * cyw;
    var cp = Math.cos(view.pitch), sp = Math.sin(view.pitch);
    var up = h * cp + b2 * sp;
    return [W / 2 + s * a2, H / 2 - s * up, b2 * cp - h * sp];
  }
  function point(rows, f, i) {
    var r = rows[f];
    if (!r || r[3 * i] === null || r[3 * i + 1] === null || r[3 * i + 2] === null) { return null; }
    return axes(r[3 * i] * q, r[3 * i + 1] * q, r[3 * i + 2] * q);
  }
  function niceStep(span) {
    var raw = span / 8, p = Math.pow(10, Math.floor(Math.log(raw) / Math.LN10)), m = raw / p;
    return (m < 2 ? 1 : m < 5 ? 2 : 5) * p;
  }
  function line(a, b) { ctx.beginPath(); ctx.moveTo(a[0], a[1]); ctx.lineTo(b[0], b[1]); ctx.stroke(); }
  function dot(p, r) { ctx.beginPath(); ctx.arc(p[0], p[1], r, 0, 2 * Math.PI); ctx.fill(); ctx.stroke(); }

  function draw() {
    var W = canvas.width, H = canvas.height, drawn = 0, lines = 0, i, p, a, b;
    ctx.clearRect(0, 0, W, H);
    ctx.fillStyle = "#ffffff"; ctx.fillRect(0, 0, W, H);
    var fr = focus(); F0 = fr[0]; R0 = fr[1];
    // floor grid (fixed in the lab, around the view's centre) at the lowest point of the take
    var ext = follow.checked ? [F0[0] - 1.3 * R0, F0[0] + 1.3 * R0, F0[1] - 1.3 * R0, F0[1] + 1.3 * R0] : [lo[0], hi[0], lo[1], hi[1]];
    var step = niceStep(Math.max(ext[1] - ext[0], ext[3] - ext[2], 1));
    var g0 = Math.floor(ext[0] / step) * step, g1 = Math.ceil(ext[1] / step) * step;
    var h0 = Math.floor(ext[2] / step) * step, h1 = Math.ceil(ext[3] / step) * step;
    ctx.strokeStyle = "#e4e4e4"; ctx.lineWidth = 1;
    for (var gx = g0; gx <= g1 + 1e-6; gx += step) { line(project([gx, h0, lo[2]], W, H), project([gx, h1, lo[2]], W, H)); }
    for (var gy = h0; gy <= h1 + 1e-6; gy += step) { line(project([g0, gy, lo[2]], W, H), project([g1, gy, lo[2]], W, H)); }
    // axes triad (lab x red, y green, z blue)
    var o = [g0, h0, lo[2]], L = step;
    var tri = [[[L, 0, 0], "#d62728"], [[0, L, 0], "#2ca02c"], [[0, 0, L], "#1f77b4"]];
    if (upSelect.value === "y") { tri = [[[L, 0, 0], "#d62728"], [[0, 0, L], "#2ca02c"], [[0, -L, 0], "#1f77b4"]]; }
    ctx.lineWidth = 2;
    for (i = 0; i < 3; i++) {
      ctx.strokeStyle = tri[i][1];
      line(project(o, W, H), project([o[0] + tri[i][0][0], o[1] + tri[i][0][1], o[2] + tri[i][0][2]], W, H));
    }
    if (showSkeleton.checked) {
      ctx.strokeStyle = "#222222"; ctx.lineWidth = 3.5; ctx.lineCap = "round";
      for (i = 0; i < S; i++) {
        if (D.parent[i] < 0) { continue; }
        a = point(D.joints, frame, D.parent[i]); b = point(D.joints, frame, i);
        if (a && b) { line(project(a, W, H), project(b, W, H)); lines++; }
      }
      for (i = 0; i < D.leaves.length; i++) {
        a = point(D.joints, frame, D.leaves[i]); b = point(D.ends, frame, i);
        if (a && b) { line(project(a, W, H), project(b, W, H)); lines++; }
      }
      ctx.fillStyle = "#ffffff"; ctx.lineWidth = 1.5;
      for (i = 0; i < S; i++) {
        p = point(D.joints, frame, i);
        if (p) { dot(project(p, W, H), 4.5); drawn++; }
      }
    }
    if (showMarkers.checked) {
      ctx.lineWidth = 0.8; ctx.strokeStyle = "#333333";
      for (i = 0; i < M; i++) {
        p = point(D.markers, frame, i);
        if (!p) { continue; }
        var s = D.marker_segment[i];
        ctx.fillStyle = s >= 0 ? D.colours[s] : "#9a9a9a";
        dot(project(p, W, H), 3.5); drawn++;
      }
    }
    var take = frame * D.step;
    label.textContent = "frame " + take + " / " + D.frames + (D.rate > 0 ? "  \u00b7  " + (take / D.rate).toFixed(2) + " s" : "");
    status.setAttribute("data-points", String(drawn));
    status.setAttribute("data-lines", String(lines));
    status.setAttribute("data-frame", String(take));
  }

  function setFrame(f) { frame = Math.max(0, Math.min(n - 1, f)); slider.value = String(frame); draw(); }
  function tick(now) {
    if (!playing) { return; }
    var per = D.rate > 0 ? D.rate / D.step : 30;
    var f = f0 + Math.floor((now - t0) / 1000 * per);
    setFrame(n > 0 ? f % n : 0);
    window.setTimeout(function () { tick(performance.now()); }, 1000 / 60);  // timers also run headless
  }
  function toggle() {
    playing = !playing;
    playBtn.textContent = playing ? "Pause" : "Play";
    if (playing) { t0 = performance.now(); f0 = frame; tick(t0); }
  }
  playBtn.addEventListener("click", toggle);
  slider.addEventListener("input", function () { if (playing) { toggle(); } setFrame(parseInt(slider.value, 10) || 0); });
  showMarkers.addEventListener("change", draw);
  showSkeleton.addEventListener("change", draw);
  follow.addEventListener("change", draw);
  upSelect.addEventListener("change", function () { extent(); draw(); });
  document.addEventListener("keydown", function (ev) {
    if (ev.code === "Space" && ev.target === document.body) { ev.preventDefault(); toggle(); }
  });
  var drag = null;
  canvas.addEventListener("mousedown", function (ev) { drag = [ev.clientX, ev.clientY, view.yaw, view.pitch]; canvas.style.cursor = "grabbing"; });
  window.addEventListener("mouseup", function () { drag = null; canvas.style.cursor = "grab"; });
  window.addEventListener("mousemove", function (ev) {
    if (!drag) { return; }
    view.yaw = drag[2] + (ev.clientX - drag[0]) * 0.01;
    view.pitch = Math.max(-1.55, Math.min(1.55, drag[3] + (ev.clientY - drag[1]) * 0.01));
    draw();
  });
  canvas.addEventListener("wheel", function (ev) {
    ev.preventDefault();
    view.zoom = Math.max(0.2, Math.min(20, view.zoom * Math.exp(-ev.deltaY * 0.001)));
    draw();
  }, { passive: false });
  canvas.addEventListener("dblclick", function () { view.yaw = -0.7; view.pitch = 0.3; view.zoom = 1.0; draw(); });

  setFrame(0);
  status.setAttribute("data-ok", "1");
})();
"""
