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

from .page import build_html, require_matplotlib

__all__ = ["build_html", "require_matplotlib"]
