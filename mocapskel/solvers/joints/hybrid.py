"""Hang's hybrid framework: MTB, solvability propagation and reduced JMV over a tree.

Hang, Lasenby & Li 2015, §II-B and §III. Every joint of a tree of marker groups
is solved, using the costly per-frame JMV optimisation as little as possible:

1. PRE-JOINT SOLVER: a group with three non-collinear markers (four- then
   three-marker groups) has a marker-trajectory basis; all its joints are
   solved by MTB. Groups whose markers are all collinear are marked *special*.
2. SOLVED-JOINT-DEPENDENT SOLVER: a solved joint is a point rigid with both of
   its groups, so it counts as a marker. A group whose markers plus solved
   joints contain three non-collinear points (a special group or a 2-marker
   group with one solved joint, a 1-marker group with two) gets a basis and
   solves its other joints ('mtb-propagated'). Repeated, in Hang's group order
   (special 4, special 3, 2-marker, 1-marker), until the system state stops
   changing.
3. REDUCED JMV SOLVER: while joints remain, one of them is solved by JMV, then
   step 2 runs again. The joint chosen is, among those whose JMV problem is
   determined (4+ points; solved joints count), the first in Hang's group
   order, then the one with the most points. (Three points, e.g. a 1-marker
   group against a 2-marker group, leave Q = 0 reachable for a family of
   radii: JMV then needs ``alpha`` > 0 or a later propagation.)

Both groups' points (markers and solved joints other than the one sought)
enter Kirk's cost Q of every joint. When both groups of a joint have a basis,
both are fitted and the two trajectories averaged with inverse-variance weights
(``combine="weighted"``, the default), averaged equally (``"average"``), or the
one with the lower Q kept (``"best"``). On Kirk's linkage with 0.5 mm noise
averaging cuts the middle-rod length error about threefold.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
from numpy.typing import ArrayLike

from .jmv import jmv_joint, jmv_joint_long
from .cost import JointFit, _seen, joint_cost
from .mtb import COLLINEAR_TOL, Basis, mtb_basis, mtb_joint

__all__ = ["TreeJoints", "solve_tree"]

#: Hang's group collections, in processing order.
CATEGORY_NAMES = ("4", "3", "special-4", "special-3", "2", "1", "0")


@dataclass(frozen=True, eq=False)
class TreeJoints:
    """All joints of a tree of marker groups.

    centres : (F, E, 3) ndarray
        Joint trajectories (edge order); NaN where a joint cannot be placed.
    method : E strings
        'mtb' (basis of real markers), 'mtb-propagated' (basis using solved
        joints) or 'jmv'; 'none' for a joint that could not be solved.
    order : (E,) int ndarray
        Edges in the order they were solved.
    cost : (E,) ndarray
        Kirk's Q of each joint (with the ``alpha`` used), over its groups'
        markers and solved joints.
    ok : (E,) bool ndarray
        Whether each joint fit succeeded.
    reason : E strings
        Why not ("" when ok).
    basis_group : (E,) int ndarray
        Group whose basis gave the joint (-1: JMV, or both groups averaged).
    special : (G,) bool ndarray
        Groups found collinear (Hang's special groups).
    category : G strings
        Each group's collection: '4', '3', 'special-4', 'special-3', '2', '1', '0'
        ('4' holds groups with four or more markers).
    log : tuple of dict
        The system state after every step: ``stage`` ('pre', 'propagate',
        'jmv'), ``group``, ``edges`` solved, ``method``, ``joint_state``
        (string of 0/1 per edge) and ``waiting`` (groups with unsolved joints).
    """

    centres: np.ndarray
    method: tuple[str, ...]
    order: np.ndarray
    cost: np.ndarray
    ok: np.ndarray
    reason: tuple[str, ...]
    basis_group: np.ndarray
    special: np.ndarray
    category: tuple[str, ...]
    log: tuple[dict[str, Any], ...]


def _noise_weight(ca: np.ndarray, cb: np.ndarray) -> float:
    """Inverse-variance weight of ``ca`` when averaging two estimates of one joint.

    The noise variances of the two per-frame estimates are told apart from
    their second differences ``D_a = M + N_a``, ``D_b = M + N_b`` (``M`` the
    motion common to both): ``E|D_a - D_b|^2 = v_a + v_b`` and
    ``E[(D_a - D_b).(D_a + D_b)] = v_a - v_b``. 0.5 when undecidable.
    """
    ok = _seen(ca) & _seen(cb)
    trip = ok[:-2] & ok[1:-1] & ok[2:]
    if trip.sum() < 10:
        return 0.5
    Da = (ca[:-2] - 2 * ca[1:-1] + ca[2:])[trip]
    Db = (cb[:-2] - 2 * cb[1:-1] + cb[2:])[trip]
    dif, tot = Da - Db, Da + Db
    s = float(np.einsum("fi,fi->", dif, dif))
    d = float(np.einsum("fi,fi->", dif, tot))
    va, vb = max(0.5 * (s + d), 1e-3 * s), max(0.5 * (s - d), 1e-3 * s)
    if not (s > 0 and np.isfinite(s) and np.isfinite(d)):
        return 0.5
    return vb / (va + vb)


def solve_tree(
    groups: Sequence[ArrayLike],
    edges: ArrayLike,
    *,
    alpha: float = 0.0,
    combine: str = "weighted",
    tol: float = COLLINEAR_TOL,
    jmv_kwargs: dict[str, Any] | None = None,
    max_frames: int | None = None,
) -> TreeJoints:
    """Solve every joint of a tree of marker groups (Hang's hybrid framework).

    Parameters
    ----------
    groups : sequence of (F, N_i, 3) ndarray
        Markers of every group (segment); NaN where not seen.
    edges : (E, 2) int array
        Joints as pairs of group indices (a tree or forest; direction ignored).
    alpha : float
        Mean-distance penalty of Kirk's Q (length units); 0 for final fits.
    combine : {"weighted", "average", "best"}
        What to do when both groups of a joint have a basis: average the two
        trajectories with inverse-variance weights estimated from their
        frame-to-frame noise (default), average them equally, or keep the
        fit with the lower Q.
    tol : float
        Relative collinearity tolerance of the bases.
    jmv_kwargs : dict, optional
        Extra keyword arguments for :func:`jmv_joint` (``max_iter``, ``tol``).
    max_frames : int, optional
        JMV fits of longer takes on this many frames spread over the take, every frame then
        placed from the fitted radii (:func:`~mocapskel.solvers.joints.jmv.jmv_joint_long`, as the
        joints stage fits its own JMV joints); None: every frame.

    Returns
    -------
    TreeJoints
    """
    G = len(groups)
    gs = [np.asarray(g, dtype=float) for g in groups]
    if G == 0:
        raise ValueError("no groups")
    F = gs[0].shape[0]
    for i, g in enumerate(gs):
        if g.ndim != 3 or g.shape[0] != F or g.shape[2] != 3:
            raise ValueError(f"group {i} must be ({F}, N, 3), got {g.shape}")
    ed = np.asarray(edges, dtype=int).reshape(-1, 2)
    E = ed.shape[0]
    if E and (ed.min() < 0 or ed.max() >= G or np.any(ed[:, 0] == ed[:, 1])):
        raise ValueError("edges must join two different valid group indices")
    if combine not in ("best", "average", "weighted"):
        raise ValueError(f"combine must be 'best', 'average' or 'weighted', got {combine!r}")
    jk = dict(jmv_kwargs or {})

    incident: list[list[int]] = [[] for _ in range(G)]
    for e, (a, b) in enumerate(ed):
        incident[a].append(e)
        incident[b].append(e)

    own = [mtb_basis(g, tol=tol) if g.shape[1] >= 3 else None for g in gs]
    special = np.array([bool(b is not None and b.special) for b in own])
    cat = []
    for i, g in enumerate(gs):
        n = g.shape[1]
        if n >= 3 and not special[i]:
            cat.append(0 if n >= 4 else 1)
        elif n >= 3:
            cat.append(2 if n >= 4 else 3)
        else:
            cat.append({2: 4, 1: 5, 0: 6}[n])

    solved = np.zeros(E, bool)
    usable = np.zeros(E, bool)  # solved and placed in at least one frame
    centres = np.full((F, E, 3), np.nan)
    method = ["none"] * E
    cost = np.full(E, np.inf)
    okv = np.zeros(E, bool)
    reason = ["not solved"] * E
    bgroup = np.full(E, -1)
    order: list[int] = []
    log: list[dict[str, Any]] = []

    def points(g: int, skip: int = -1) -> tuple[np.ndarray, int]:
        """Markers of g followed by its solved joints (except ``skip``); and the joint count."""
        js = [centres[:, e][:, None, :] for e in incident[g] if usable[e] and e != skip]
        return (np.concatenate([gs[g], *js], axis=1) if js else gs[g]), len(js)

    cache: dict[tuple[int, tuple[int, ...]], Basis | None] = {}

    def basis_of(g: int) -> tuple[Basis | None, bool]:
        """The group's basis and whether it needed solved joints."""
        if own[g] is not None and own[g]:
            return own[g], False
        key = (g, tuple(e for e in incident[g] if usable[e]))
        if not key[1] or gs[g].shape[1] + len(key[1]) < 3:
            return None, False
        if key not in cache:
            b = mtb_basis(points(g)[0], tol=tol)
            cache[key] = b if b else None
        return cache[key], cache[key] is not None

    def waiting() -> list[int]:
        return [g for g in range(G) if any(not solved[e] for e in incident[g])]

    def record(stage: str, g: int, es: list[int], meth: str) -> None:
        log.append({
            "stage": stage, "group": int(g), "edges": [int(e) for e in es], "method": meth,
            "joint_state": "".join("1" if s else "0" for s in solved),
            "waiting": waiting(),
        })

    def store(e: int, fit: JointFit, meth: str, bg: int) -> None:
        centres[:, e] = fit.centre
        method[e] = meth
        cost[e] = fit.cost
        okv[e] = bool(fit.ok)
        reason[e] = fit.reason
        bgroup[e] = bg
        solved[e] = True
        usable[e] = bool(np.isfinite(fit.centre).all(-1).any())
        order.append(e)

    def solve_mtb(e: int) -> str | None:
        a, b = ed[e]
        pa, _ = points(a, e)
        pb, _ = points(b, e)
        fits: list[tuple[JointFit, int, bool]] = []
        for g, side in ((a, "a"), (b, "b")):
            bas, prop = basis_of(g)
            if bas is not None:
                fit = mtb_joint(bas, pa, pb, alpha=alpha, basis_side=side)
                fits.append((fit, int(g), prop))
                if fit.ok and fit.n_iter == 0 and alpha == 0.0:
                    break  # exact to rounding from its closed form: the other side can only agree
        if not fits:
            return None
        good = [f for f in fits if f[0].ok] or fits
        if combine in ("average", "weighted") and len(good) == 2:
            ca, cb = good[0][0].centre, good[1][0].centre
            wa = _noise_weight(ca, cb) if combine == "weighted" else 0.5
            c = wa * ca + (1.0 - wa) * cb
            one = np.isfinite(ca).all(-1) ^ np.isfinite(cb).all(-1)
            c[one] = np.where(np.isfinite(ca[one]), ca[one], cb[one])
            both = np.concatenate([pa, pb], axis=1)
            allok = good[0][0].ok and good[1][0].ok
            why = "" if allok else (good[0][0].reason or good[1][0].reason)
            fit = JointFit(c, joint_cost(c, both, alpha), good[0][0].n_iter + good[1][0].n_iter, allok, why)
            meth = "mtb-propagated" if (good[0][2] or good[1][2]) else "mtb"
            store(e, fit, meth, -1)
            return meth
        fit, g, prop = min(good, key=lambda f: f[0].cost)
        meth = "mtb-propagated" if prop else "mtb"
        store(e, fit, meth, g)
        return meth

    # 1. PRE-JOINT SOLVER: 4- then 3-marker (non-special) groups.
    for g in sorted((g for g in range(G) if cat[g] in (0, 1)), key=lambda g: cat[g]):
        es = [e for e in incident[g] if not solved[e]]
        done = [e for e in es if solve_mtb(e) is not None]
        if done:
            record("pre", g, done, method[done[0]])

    # 2. SOLVED-JOINT-DEPENDENT SOLVER, looped until the state stops changing.
    def propagate() -> None:
        changed = True
        while changed:
            changed = False
            for g in sorted(range(G), key=lambda g: cat[g]):
                es = [e for e in incident[g] if not solved[e]]
                if not es:
                    continue
                bas, _ = basis_of(g)
                if bas is None:
                    continue
                done = []
                for e in es:
                    meth = solve_mtb(e)
                    if meth is not None:
                        done.append(e)
                if done:
                    record("propagate", g, done, method[done[0]])
                    changed = True

    propagate()

    # 3. REDUCED JMV SOLVER: one joint at a time, then propagate again.
    while not solved.all():
        cand = []
        for e in np.flatnonzero(~solved):
            a, b = ed[e]
            pa, ja = points(a, e)
            pb, jb = points(b, e)
            n = pa.shape[1] + pb.shape[1]
            # determined problems (4+ points) first, then Hang's group order
            cand.append((n < 4, min(cat[a], cat[b]), -n, -(ja + jb), int(e)))
        cand.sort()
        e = cand[0][-1]
        a, b = ed[e]
        pa, _ = points(a, e)
        pb, _ = points(b, e)
        if max_frames is None:
            fit = jmv_joint(pa, pb, alpha=alpha, **jk)
        else:
            fit = jmv_joint_long(pa, pb, alpha=alpha, max_frames=max_frames, **jk)
        store(e, fit, "jmv", -1)
        record("jmv", int(a if cat[a] <= cat[b] else b), [e], "jmv")
        propagate()

    return TreeJoints(
        centres=centres,
        method=tuple(method),
        order=np.array(order, dtype=int),
        cost=cost,
        ok=okv,
        reason=tuple(reason),
        basis_group=bgroup,
        special=special,
        category=tuple(CATEGORY_NAMES[c] for c in cat),
        log=tuple(log),
    )
