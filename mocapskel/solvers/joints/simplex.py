"""Nelder and Mead's simplex search, for the few-unknown minimisations of the joints stage (a joint held
in a segment: three unknowns). Written out so that a fit does not import ``scipy.optimize`` (about a
fifth of a second); the steps are scipy's non-adaptive ones (reflection 1, expansion 2, contraction and
shrink 1/2), in its order."""
from __future__ import annotations

from typing import Callable

import numpy as np


def nelder_mead(f: Callable[[np.ndarray], float], simplex: np.ndarray, *, xatol: float = 1e-4,
                fatol: float = 1e-4, max_iter: int | None = None, max_calls: int | None = None) -> np.ndarray:
    """The best vertex of the simplex (N + 1, N) after Nelder-Mead steps on ``f``: stops when every vertex
    lies within ``xatol`` of the best in each coordinate and their values within ``fatol`` of its value,
    or after ``max_iter`` steps or ``max_calls`` evaluations (both 200 N by default)."""
    sim = np.array(simplex, dtype=float)
    N = sim.shape[1]
    max_iter = 200 * N if max_iter is None else max_iter
    max_calls = 200 * N if max_calls is None else max_calls
    calls = [0]

    def fun(x: np.ndarray) -> float:
        calls[0] += 1
        return float(f(x))

    fsim = np.array([fun(x) for x in sim])
    order = np.argsort(fsim)
    sim, fsim = sim[order], fsim[order]
    it = 1
    while calls[0] < max_calls and it < max_iter:
        if np.max(np.abs(sim[1:] - sim[0])) <= xatol and np.max(np.abs(fsim[0] - fsim[1:])) <= fatol:
            break
        xbar = sim[:-1].mean(0)
        xr = 2.0 * xbar - sim[-1]
        fxr = fun(xr)
        shrink = False
        if fxr < fsim[0]:
            xe = 3.0 * xbar - 2.0 * sim[-1]
            fxe = fun(xe)
            sim[-1], fsim[-1] = (xe, fxe) if fxe < fxr else (xr, fxr)
        elif fxr < fsim[-2]:
            sim[-1], fsim[-1] = xr, fxr
        elif fxr < fsim[-1]:  # outside contraction
            xc = 1.5 * xbar - 0.5 * sim[-1]
            fxc = fun(xc)
            if fxc <= fxr:
                sim[-1], fsim[-1] = xc, fxc
            else:
                shrink = True
        else:  # inside contraction
            xcc = 0.5 * xbar + 0.5 * sim[-1]
            fxcc = fun(xcc)
            if fxcc < fsim[-1]:
                sim[-1], fsim[-1] = xcc, fxcc
            else:
                shrink = True
        if shrink:
            for j in range(1, N + 1):
                sim[j] = sim[0] + 0.5 * (sim[j] - sim[0])
                fsim[j] = fun(sim[j])
        it += 1
        order = np.argsort(fsim)
        sim, fsim = sim[order], fsim[order]
    return sim[0]
