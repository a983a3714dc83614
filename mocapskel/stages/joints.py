"""Joints: a joint-centre trajectory for every edge of the tree.

Methods (``Params.method``):

- ``mtb``: Hang et al. 2015 — marker-trajectory bases with solvability
  propagation, JMV only where nothing else can (the hybrid framework);
- ``jmv``: Kirk et al. 2005 — joint-marker-variance optimisation, every joint;
- ``auto``: per joint, the best available (see :func:`run`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..artifacts import Joints, Topology
from ..errors import DataError
from ..solvers.hybrid import solve_tree
from ..solvers.jmv import jmv_joint, joint_cost

VERSION = 1

METHODS = ("auto", "jmv", "mtb", "sphere", "score")


@dataclass(frozen=True)
class Params:
    method: str = "auto"
    alpha: float = 0.0
    """Kirk's distance penalty in the final fit (0: dropped, as the paper's discussion advises)."""


def run(topology: Topology, params: Params = Params()) -> Joints:
    """Estimate every joint centre over all frames."""
    if params.method not in METHODS:
        raise ValueError(f"unknown joint method {params.method!r}")
    seg = topology.segments
    pts = seg.markers.points
    S = seg.n_segments
    groups = [pts[:, seg.members(s)] for s in range(S)]
    edges = topology.edges
    E = edges.shape[0]
    F = pts.shape[0]
    per_joint: list[dict] = [{} for _ in range(E)]
    warnings: list[str] = []
    if params.method == "jmv":
        centres = np.full((F, E, 3), np.nan)
        methods = []
        for e, (a, b) in enumerate(edges):
            fit = jmv_joint(groups[a], groups[b], alpha=params.alpha)
            centres[:, e] = fit.centre
            methods.append("jmv")
            if not fit.ok:
                per_joint[e]["note"] = fit.reason
    else:
        tree = solve_tree(groups, edges, alpha=params.alpha)
        centres = tree.centres
        methods = list(tree.method)
        for e in range(E):
            per_joint[e]["why"] = _why(tree.method[e], tree.category, edges[e])
            if not tree.ok[e]:
                per_joint[e]["note"] = tree.reason[e]
    residual = np.full(E, np.nan)
    for e, (a, b) in enumerate(edges):
        both = np.concatenate([groups[a], groups[b]], axis=1)
        if np.isfinite(centres[:, e]).any():
            residual[e] = np.sqrt(joint_cost(centres[:, e], both, alpha=0.0))
        else:
            warnings.append(f"joint {a}-{b} could not be placed in any frame")
    if not np.isfinite(centres).any():
        raise DataError("no joint centre could be estimated", seg.markers.source or None)
    info = {"version": VERSION, "method": params.method, "per_joint": per_joint, "warnings": warnings}
    return Joints(topology=topology, centres=centres, method=tuple(methods), residual=residual, info=info)


def _why(method: str, category: tuple[str, ...], edge: np.ndarray) -> str:
    a, b = int(edge[0]), int(edge[1])
    cats = f"groups of {category[a]} and {category[b]} markers"
    return {
        "mtb": f"closed form: a group has 3+ non-collinear markers ({cats})",
        "mtb-propagated": f"closed form with solved joints as markers ({cats})",
        "jmv": f"no basis available, joint-marker-variance optimisation ({cats})",
    }.get(method, cats)
