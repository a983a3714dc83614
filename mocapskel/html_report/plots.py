"""The HTML report's plots, drawn with matplotlib's Agg renderer (no pyplot) and embedded as base64 PNG."""
from __future__ import annotations

import base64
import html
import io
import math
from typing import Any

import numpy as np

from ..artifacts import Segments, Topology
from .colours import colour

#: Time series with more samples than this are binned before plotting (line: rms per bin, band: min to max).
MAX_PLOT_SAMPLES = 4000
_DPI = 100


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


def _plot_uncertainty(report: dict) -> str:
    """Per joint, its standard deviations (mm, log scale) along its three principal directions, the
    prior's standard deviation beside them; a bar is red where the prior sets the joint."""
    rows = [(f"{j.get('parent')}–{j.get('child')}", j["uncertainty"]) for j in report.get("joints", [])
            if j.get("uncertainty")]
    if not rows:
        return ""
    above = float(((report.get("uncertainty") or {}).get("prior") or {}).get("set_by_prior_above", 0.5))
    fig = _figure(9.0, 0.9 + 0.42 * len(rows))
    ax = fig.add_subplot(1, 1, 1)
    h = 0.26
    for r, (_, u) in enumerate(rows):
        for k in range(3):
            sd = max(float(u["sd_mm"][k]), 1e-3)
            red = float(u["prior_share"][k]) > above
            ax.barh(r + (k - 1) * h, sd, height=h * 0.9, color="#d62728" if red else ("#1f77b4", "#4f97d4", "#8fbfe4")[k])
        ax.plot([u["prior_sd_mm"]] * 2, [r - 1.5 * h, r + 1.5 * h], color="#222222", lw=1.5)
    ax.set_xscale("log")
    ax.set_yticks(range(len(rows)), [n for n, _ in rows], fontsize=8)
    ax.invert_yaxis()
    ax.set_xlabel("sd (mm) along the joint's principal directions, largest first; black tick: the prior's sd; "
                  "red: set by the prior", fontsize=8)
    ax.grid(True, axis="x", which="both", alpha=0.3)
    return _png(fig, "per-joint uncertainty: standard deviation along each principal direction")
