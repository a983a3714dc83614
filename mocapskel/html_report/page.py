"""The HTML report's page: the summary, warnings and tables, and the assembly of every section into one
self-contained page."""
from __future__ import annotations

import html
import importlib
import math
from typing import Any

import numpy as np

from ..artifacts import Motion
from ..errors import UsageError
from .colours import colour
from .data import _chain, joint_residual_series, segment_residual_series
from .plots import _plot_dist_std, _plot_eigengap, _plot_graph, _plot_series, _plot_uncertainty
from .template import _CSS, _PAGE, _VIEWER_HTML, _VIEWER_JS
from .viewer import MAX_VIEWER_FRAMES, _json_for_script, viewer_data

__all__ = ["build_html", "require_matplotlib"]


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


def _uncertainty(report: dict) -> str:
    """The joints' uncertainty: the bar chart, then a table with the motion that would place each joint
    the prior sets."""
    unc = report.get("uncertainty")
    if not unc:
        return '<p class="note">This fit carries no joint uncertainty (the skeleton was not refined).</p>'
    rows = []
    for j in report.get("joints", []):
        u = j.get("uncertainty")
        if not u:
            continue
        rows.append([_fmt(j.get("parent")), _fmt(j.get("child")), " / ".join(f"{x:.3g}" for x in u["sd_mm"]),
                     _fmt(u.get("skin_sd_mm")), " / ".join(f"{x:.2f}" for x in u["prior_share"]), _fmt(u["prior_sd_mm"]),
                     "yes" if u["set_by_prior"] else "no", _fmt(u.get("motion_to_fix"))])
    prior = unc.get("prior") or {}
    note = (f'<p class="note">Each joint\'s position relative to its child segment\'s markers: the standard deviation '
            f"along its three principal directions (the Laplace approximation of the skeleton model, the take's noise "
            f"{_fmt(unc.get('noise_mm'))} mm per coordinate from {_fmt(unc.get('frames'))} frames; of the residual, a share of "
            f"{_fmt(unc.get('skin_share'))} follows the joint angles: skin that slides with the joints, which that noise does not "
            "describe; the standard deviations include how far such skin can have moved each joint, its skin sd), and the share of the "
            f"precision along each that comes from the prior (sd {_fmt(prior.get('sd_per_segment_size'))} of the child "
            f"segment's size); a joint is set by the prior where that share exceeds {_fmt(prior.get('set_by_prior_above'))}. "
            "The 3-D view draws each joint's principal axes, two sd long.</p>")
    return (_plot_uncertainty(report) + note
            + _table(["parent", "child", "sd (mm)", "skin sd (mm)", "prior share", "prior sd (mm)", "set by prior", "to place it"], rows))


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
    sections.append(("uncertainty", "Joint uncertainty", _uncertainty(report)))

    nav = " · ".join(f'<a href="#{sid}">{html.escape(h)}</a>' for sid, h, _ in sections)
    body = "\n".join(f'<section id="{sid}"><h2>{html.escape(h)}</h2>\n{b}\n</section>' for sid, h, b in sections)
    return _PAGE.format(title=html.escape(title), nav=nav, body=body, css=_CSS)
