"""The segment colours of the HTML report, shared by its plots, its 3-D view and its tables."""
from __future__ import annotations

__all__ = ["PALETTE"]

#: Segment colours (matplotlib's tab20 order, dark shades first), shared by plots and the 3-D view.
PALETTE: tuple[str, ...] = (
    "#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f",
    "#bcbd22", "#17becf", "#aec7e8", "#ffbb78", "#98df8a", "#ff9896", "#c5b0d5", "#c49c94",
    "#f7b6d2", "#c7c7c7", "#dbdb8d", "#9edae5",
)
_LEFT_OUT_COLOUR = "#9a9a9a"


def colour(s: int) -> str:
    """The colour of segment ``s`` (grey for ``-1``: a marker on no segment)."""
    return _LEFT_OUT_COLOUR if s < 0 else PALETTE[s % len(PALETTE)]
