"""Merge-ids: labels that are one physical marker become one (Kirk et al. 2005, §4).

Passive systems give a marker a new label after every gap. Two labels can be
one marker only if they are never visible in the same frame. This version
passes labels through unchanged and records how many labels there are against
the most markers seen in one frame (Kirk's count of physical markers), so the
report shows when a take looks relabelled.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..artifacts import Markers

VERSION = 1


@dataclass(frozen=True)
class Params:
    enabled: bool = True


def run(markers: Markers, params: Params = Params()) -> Markers:
    """Return the markers with ``stage="merge-ids"`` and ``info["merge_ids"]`` filled in."""
    vis = np.isfinite(markers.points).all(axis=2)
    physical = int(vis.sum(axis=1).max()) if vis.size else 0
    info = dict(markers.info)
    info["merge_ids"] = {
        "version": VERSION,
        "labels": markers.n_markers,
        "physical_markers": physical,
        "merged": {},
        "looks_relabelled": bool(markers.n_markers > 1.2 * max(physical, 1)),
    }
    return replace(markers, stage="merge-ids", info=info)
