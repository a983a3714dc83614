"""A factor-graph library (gtsam) against our own solver of the skeleton model: speed, MAP, uncertainty.

    python -m bench.factor_graph [--chain-seeds 1-4] [--human-seeds 1-2] [--frames 300] [--large 1200]

gtsam is optional (``pip install gtsam==4.3.0``, not a dependency of mocapskel): without it this prints a
note and exits 0.

The problem: a generated take (a hinge chain from :func:`~mocapskel.synth.chains.hinge_chain`, 1 mm
noise; the human ROM of :func:`~mocapskel.synth.presets.active_rom`, 48 markers) goes through the
pipeline up to the rigid stage with ``joint_model="map"``; the first call of that stage's MAP
refinement (:func:`~mocapskel.solvers.model.calibrate.refine_skeleton` from
:func:`~mocapskel.solvers.model.joint_map.map_refine`) is recorded: its start (the rigid stage's skeleton
before refinement and the poses IK gives it on the refinement's frames), its frames and its prior
(a Gaussian on every joint relative to the marker centroid of each of its two segments, weights
``prior_weights``, centred on ``anchor``). Both solvers get exactly that problem:

- ours: ``refine_skeleton`` with the recorded arguments, then
  :func:`~mocapskel.solvers.model.uncertainty.joint_uncertainty` at its result, with and without the
  correction for the noise's part of the curvature;
- gtsam: per frame a ``Point3`` (root position) and a ``Rot3`` per segment (global rotation), constants
  ``Point3`` (bone offsets, marker offsets), one ``CustomFactor`` per seen marker per frame (analytic
  Jacobians, unit isotropic noise: its error is half our cost), one linear ``CustomFactor`` per prior
  term (isotropic, sigma = 1 / sqrt(weight)); the same gauge as ours (the reference frame's rotations
  and the root's first joint's offset held: constants, not variables). Solved twice from the same start:
  by gtsam's ``LevenbergMarquardtOptimizer`` (Marquardt's diagonal damping, relative tolerance and
  iteration cap as ours; ``--lm-cap`` / ``--human-lm-cap`` cut it short where it is too slow to wait for),
  and by :func:`lm_loop`, Levenberg-Marquardt driven from Python on gtsam's linearisation and
  elimination (the same damping rule as ours), which isolates the cost of gtsam's solver from the way
  its optimizer calls Python factors. Its uncertainty: ``gtsam.Marginals`` of
  a second graph at its MAP, the marker factors' sigma the noise from its residual (our degrees of
  freedom), the joints' prior of ``joint_uncertainty`` (sd 0.5 x the child segment's size, on the joint
  relative to its child's markers, a linear factor on the child's marker offsets) and a weak prior on
  every rotation (:data:`WEAK_ROT_SD`, as ours damps poses the markers do not fix).
  The covariance of each joint relative to its child's markers is that factor's map applied to the
  joint marginal of the child's marker offsets.

Compared: joints (every frame of the fit, lab) of the two MAPs against each other and against the truth,
the objective (squared marker residuals plus the weighted prior, mm^2), iterations, the sd along each
joint's principal axes (ours with and without the noise correction against gtsam), the coverage of the
truth by the 95 % region (as :mod:`bench.uncertainty`), wall time on one thread and peak memory.
"""
from __future__ import annotations

import os

for _v in ("MOCAPSKEL_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import contextlib  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass, replace  # noqa: E402

import numpy as np  # noqa: E402

try:
    import gtsam
except ImportError:  # optional: the bench says so and stops
    gtsam = None

from bench.common import machine  # noqa: E402
from bench.uncertainty import CHI2_3_95, joint_errors  # noqa: E402
from mocapskel.evaluate import segment_map  # noqa: E402
from mocapskel.pipeline import make_params, run_until  # noqa: E402
from mocapskel.solvers.model import calibrate, joint_map  # noqa: E402
from mocapskel.solvers.model import uncertainty as unc_mod  # noqa: E402
from mocapskel.stages import rigid  # noqa: E402
from mocapskel.synth.chains import hinge_chain  # noqa: E402
from mocapskel.synth.presets import active_rom, make  # noqa: E402


# --------------------------------------------------------------------------------------------------
# the problem, as the rigid stage poses it


@dataclass
class Case:
    """One MAP problem of the rigid stage: the arguments of its ``refine_skeleton`` call, the frames
    (indices into the take), the start skeleton and the take's truth."""

    name: str
    args: tuple
    kwargs: dict
    frames: np.ndarray
    start: object
    truth: object


class _Stop(Exception):
    pass


def capture(markers, truth, name: str, refine_frames: int = 300) -> Case:
    """Run the pipeline to the rigid stage's MAP refinement and record its first problem (then stop)."""
    params = make_params()
    joints = run_until(markers, "joints", params).artifact
    got = {}
    real_refine, real_frames = joint_map.refine_skeleton, joint_map.refinement_frames

    def frames(skel, n):
        got["frames"] = real_frames(skel, n)
        got["start"] = skel
        return got["frames"]

    def refine(*args, **kwargs):
        got["args"], got["kwargs"] = args, kwargs
        raise _Stop

    joint_map.refine_skeleton, joint_map.refinement_frames = refine, frames
    try:
        # rigid joints: the factor graph built from the recorded problem has no soft joints' offsets
        rigid.run(joints, replace(params.get("rigid") or rigid.Params(), joint_model="map", uncertainty=False,
                                  refine_frames=refine_frames, soft_sigma=0.0))
    except _Stop:
        pass
    finally:
        joint_map.refine_skeleton, joint_map.refinement_frames = real_refine, real_frames
    if "args" not in got:
        raise RuntimeError(f"{name}: the rigid stage did not refine")
    return Case(name, got["args"], got["kwargs"], got["frames"], got["start"], truth)


def _unpack(case: Case):
    parent, origin, seg, local, obs, rot, root = case.args
    return (np.asarray(parent), np.asarray(origin, float), np.asarray(seg), np.asarray(local, float),
            np.asarray(obs, float), np.asarray(rot, float), np.asarray(root, float))


def objective(pr, A, u0, p, R, d, l) -> float:
    """Our objective, computed outside both solvers: squared marker residuals plus the weighted priors."""
    r = A @ calibrate._pack(pr, d, l) - u0 if A.shape[0] else np.zeros(0)
    return pr.cost(p, R, d, l) + float(r @ r)


@contextlib.contextmanager
def peak_rss():
    """Peak resident memory (MB) of the block over what was resident when it began (Linux: VmHWM reset)."""
    out = {"mb": float("nan")}

    def status(key):
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith(key):
                    return int(line.split()[1]) / 1024.0
        return float("nan")

    try:
        import ctypes

        ctypes.CDLL("libc.so.6").malloc_trim(0)  # freed heap back to the system, so that reuse shows as a rise
    except (OSError, AttributeError):
        pass
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        base = status("VmRSS")
    except OSError:
        base = None
    yield out
    if base is not None:
        out["mb"] = status("VmHWM") - base


# --------------------------------------------------------------------------------------------------
# the same model in gtsam


class GraphModel:
    """The skeleton model of ``refine_skeleton`` as a gtsam factor graph (see the module docstring)."""

    def __init__(self, parent, origin, seg, local, obs, rot, root, *, ref_frame, prior_weights, anchor):
        self.pr = pr = calibrate._Problem(parent, seg, obs)
        self.parent, self.seg, self.ref = parent, seg, int(ref_frame)
        self.F, self.S = obs.shape[0], len(parent)
        self.d0, self.l0 = pr.offsets(origin), local.copy()
        self.R0, self.p0 = rot.copy(), root.copy()
        # gauge: the root's first joint's offset fixed (as ours), the reference frame's rotations fixed
        rk0 = [c for c in pr.kids if parent[c] == pr.root]
        self.fixed_d = rk0[0] if rk0 else None
        self.A = calibrate._joint_prior_operator(pr, parent, weights=np.asarray(prior_weights, float))
        a_origin, a_local = anchor
        self.u0 = self.A @ calibrate._pack(pr, pr.offsets(a_origin),
                                           np.asarray(a_local, float))
        self.seen = np.isfinite(obs).all(-1)
        self.obs = obs
        self.calls = {"n_lin": 0, "n_err": 0, "t_lin": 0.0, "t_err": 0.0}

    # keys
    def kP(self, f):
        return gtsam.symbol("p", f)

    def kR(self, f, s):
        return gtsam.symbol("r", f * self.S + s)

    def kD(self, c):
        return gtsam.symbol("d", c)

    def kL(self, m):
        return gtsam.symbol("l", m)

    def values(self, p, R, d, l) -> "gtsam.Values":
        v = gtsam.Values()
        pr = self.pr
        for f in range(self.F):
            v.insert(self.kP(f), np.asarray(p[f], float))
        for f, s in self.rot_vars:
            v.insert(self.kR(f, s), gtsam.Rot3(R[f, s]))
        for c in pr.kids:
            if c != self.fixed_d:
                v.insert(self.kD(c), np.asarray(d[c], float))
        for m in pr.used:
            v.insert(self.kL(int(m)), np.asarray(l[m], float))
        return v

    def read(self, v):
        """(p, R, d, l) from gtsam values (constants where not variables)."""
        pr = self.pr
        p = np.array([v.atPoint3(self.kP(f)) for f in range(self.F)])
        R = self.R0.copy()
        for f, s in self.rot_vars:
            R[f, s] = v.atRot3(self.kR(f, s)).matrix()
        d = self.d0.copy()
        for c in pr.kids:
            if c != self.fixed_d:
                d[c] = v.atPoint3(self.kD(c))
        l = self.l0.copy()
        for m in pr.used:
            l[m] = v.atPoint3(self.kL(int(m)))
        return p, R, d, l

    def _marker_factor(self, f, m, sigma):
        """The factor of marker ``m`` seen in frame ``f``: x = p + sum R_parent(c) d_c + R_t l_m - y."""
        pr, parent = self.pr, self.parent
        t = int(self.seg[m])
        path = pr.path[t]
        ref = f == self.ref
        y = self.obs[f, m]
        # the keys, and for each where its Jacobian goes: rotations of the path, bones on it, the marker
        rot_keys = [None if ref else self.kR(f, s) for s in path]
        bone_keys = [None if c == self.fixed_d else self.kD(c) for c in path[1:]]
        keys = [self.kP(f)] + [k for k in rot_keys if k is not None] + [k for k in bone_keys if k is not None] + [self.kL(m)]
        R_const = [self.R0[f, s] for s in path]
        d_const = [self.d0[c] for c in path[1:]]
        kp, kl = self.kP(f), self.kL(m)
        calls = self.calls
        perf = time.perf_counter

        def error(this, v, H):
            t0 = perf()
            Rs = [R_const[i] if k is None else v.atRot3(k).matrix() for i, k in enumerate(rot_keys)]
            ds = [d_const[i] if k is None else v.atPoint3(k) for i, k in enumerate(bone_keys)]
            lm = v.atPoint3(kl)
            x = v.atPoint3(kp) + Rs[-1] @ lm
            for i in range(len(ds)):
                x = x + Rs[i] @ ds[i]
            if H is not None:
                # d(R u)/d(omega) = -R hat(u) for R Exp(omega) (gtsam's Rot3 retraction)
                H[0] = np.eye(3)
                j = 1
                for i, k in enumerate(rot_keys):
                    if k is not None:
                        u = ds[i] if i < len(ds) else lm
                        H[j] = -Rs[i] @ _hat3(u)
                        j += 1
                for i, k in enumerate(bone_keys):
                    if k is not None:
                        H[j] = Rs[i]
                        j += 1
                H[j] = Rs[-1]
                calls["n_lin"] += 1
                calls["t_lin"] += perf() - t0
            else:
                calls["n_err"] += 1
                calls["t_err"] += perf() - t0
            return x - y

        return gtsam.CustomFactor(gtsam.noiseModel.Isotropic.Sigma(3, sigma), keys, error)

    def _linear_factor(self, row_keys, blocks, target, sigma):
        """A linear factor sum_k B_k x_k - target on Point3 keys (``None``: a constant ``x``), isotropic sigma."""
        keys = [k for k, _, _ in row_keys if k is not None]

        def error(this, v, H):
            e = -target.copy()
            j = 0
            for (k, const, _), B in zip(row_keys, blocks):
                e = e + B @ (const if k is None else v.atPoint3(k))
                if k is not None and H is not None:
                    H[j] = B
                    j += 1
            return e

        return gtsam.CustomFactor(gtsam.noiseModel.Isotropic.Sigma(target.size, sigma), keys, error)

    def build(self, sigma: float = 1.0, priors: str = "map", prior_sd=None, l_at=None) -> "gtsam.NonlinearFactorGraph":
        """The graph: a factor per seen marker per frame (noise ``sigma``) and the priors: ``"map"`` those of
        the refinement (on every joint relative to its two segments' marker centroids), ``"uncertainty"``
        those of :func:`joint_uncertainty` (sd ``prior_sd`` per joint, relative to its child's markers, the
        map linearised at ``l_at``) and a weak prior on every rotation."""
        pr = self.pr
        g = gtsam.NonlinearFactorGraph()
        for f in range(self.F):
            for m in pr.used:
                if self.seen[f, m]:
                    g.add(self._marker_factor(f, int(m), sigma))
        if priors == "map":
            # each 3-row block of A is one prior term: on d_c (maybe) and some markers' offsets
            for b in range(0, self.A.shape[0], 3):
                rows = self.A[b : b + 3]
                w = float(np.abs(rows).max())
                items, blocks = [], []
                for c in pr.kids:
                    B = rows[:, pr.gi[c] : pr.gi[c] + 3]
                    if np.abs(B).max() > 0:
                        items.append((None if c == self.fixed_d else self.kD(c), self.d0[c], None))
                        blocks.append(B / w)
                for m in pr.used:
                    B = rows[:, pr.gl[int(m)] : pr.gl[int(m)] + 3]
                    if np.abs(B).max() > 0:
                        items.append((self.kL(int(m)), None, None))
                        blocks.append(B / w)
                g.add(self._linear_factor(items, blocks, self.u0[b : b + 3] / w, 1.0 / w))
        else:
            for k, c in enumerate(pr.kids):
                Ac, _ = unc_mod._joint_operator(pr, l_at, c)
                ms = [int(m) for m in pr.used if pr.seg[m] == c]
                if not ms:
                    continue
                items = [(self.kL(m), None, None) for m in ms]
                blocks = [Ac[:, pr.gl[m] : pr.gl[m] + 3] for m in ms]
                target = sum(B @ l_at[m] for B, m in zip(blocks, ms))
                g.add(self._linear_factor(items, blocks, target, float(prior_sd[k])))
            weak = gtsam.noiseModel.Isotropic.Sigma(3, WEAK_ROT_SD)
            for f, s in self.rot_vars:
                g.add(gtsam.PriorFactorRot3(self.kR(f, s), gtsam.Rot3(self.R0[f, s]), weak))
        return g

    @property
    def rot_vars(self) -> list[tuple[int, int]]:
        """(frame, segment) rotations that are variables: every frame but the reference, every segment some
        seen marker of that frame depends on (the others meet no factor and keep their start, as in ours)."""
        if not hasattr(self, "_rot_vars"):
            pr = self.pr
            below = np.zeros((pr.used.size, self.S), dtype=bool)
            below[pr.fi, pr.fs] = True
            touched = self.seen[:, pr.used].astype(float) @ below > 0  # (F, S)
            touched[self.ref] = False
            self._rot_vars = [(int(f), int(s)) for f, s in zip(*np.nonzero(touched))]
        return self._rot_vars


def lm_loop(graph, v0, iterations: int, tol: float):
    """Levenberg-Marquardt driven from Python on gtsam's linearisation and elimination, the damping and its
    updates as ours (Marquardt's diagonal, Nielsen's rule); the values stay owned by Python, so gtsam
    hands each Python factor the values without copying them. Returns (values, iterations, seconds in
    the linear solves)."""
    v = v0
    cost = 2.0 * graph.error(v)
    lam, nu = 1e-4, 2.0
    ordering = None
    it = 0
    t_solve = 0.0
    for it in range(1, iterations + 1):
        gfg = graph.linearize(v)
        if ordering is None:
            ordering = gtsam.Ordering.ColamdGaussianFactorGraph(gfg)
        # the Gauss-Newton matrix's diagonal: column sums of the squared Jacobian (every variable has 3 columns,
        # in the order of the sorted keys, numbered from 1; the last column is the right-hand side)
        keys = sorted(gfg.keyVector())
        ij = gfg.sparseJacobian_()
        col = ij[1].astype(int) - 1
        inside = col < 3 * len(keys)
        d = np.bincount(col[inside], ij[2][inside] ** 2, minlength=3 * len(keys)).reshape(-1, 3)
        dvals = list(d)
        while True:
            t = time.perf_counter()
            damped = gtsam.GaussianFactorGraph()
            damped.push_back(gfg)
            for k, dv in zip(keys, dvals):
                damped.add(gtsam.JacobianFactor(k, np.diag(np.sqrt(lam * dv + 1e-9)), np.zeros(dv.size),
                                                gtsam.noiseModel.Unit.Create(dv.size)))
            try:
                delta = damped.optimize(ordering)
            except RuntimeError:  # gtsam found the damped system indeterminate (a pose the markers hardly fix)
                delta = None
            t_solve += time.perf_counter() - t
            if delta is not None:
                v1 = v.retract(delta)
                c1 = 2.0 * graph.error(v1)
                pred = cost - 2.0 * gfg.error(delta)
                if c1 < cost:
                    break
            lam *= nu
            nu *= 2.0
            if lam > 1e8:
                return v, it, t_solve
        rel = (cost - c1) / max(cost, 1e-300)
        rho = (cost - c1) / pred if pred > 0 else 1.0
        v, cost = v1, c1
        lam = max(lam * max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3), 1e-9)
        nu = 2.0
        if rel < tol:
            break
    return v, it, t_solve


#: Standard deviation (rad) of the prior on every rotation in the marginals' graph: a ridge (0.01 rad^-2,
#: against 1e4 and more from a marker 100 mm out at 1 mm noise) where the markers leave a pose free (a
#: segment with one marker seen and nothing below it seen: its turn about the line through the marker), as
#: ours damps its pose blocks; with 1000 rad gtsam's elimination found such a pose indeterminate.
WEAK_ROT_SD = 10.0


def _hat3(u):
    return np.array([[0.0, -u[2], u[1]], [u[2], 0.0, -u[0]], [-u[1], u[0], 0.0]])


# --------------------------------------------------------------------------------------------------
# one case, both solvers


def _to_skeleton(start, parent, origin_in, seg, p, R, d, l, ref):
    """The skeleton of a solution in the rest gauge (identity rotations at ``ref``), as refine_skeleton
    returns it, and the rotations Q (S, 3, 3) at ``ref`` that took it there."""
    Q = R[ref].copy()
    order = calibrate.depth_first_order(parent)
    origin = np.array(origin_in, float)
    l2 = l.copy()
    ok = (seg >= 0) & np.isfinite(l).all(1)
    l2[ok] = np.einsum("mij,mj->mi", Q[seg[ok]], l[ok])
    root = int(np.flatnonzero(parent < 0)[0])
    origin[root] = p[ref]
    for s in order:
        if parent[s] >= 0:
            origin[s] = origin[parent[s]] + Q[parent[s]] @ d[s]
    return replace(start, origin=origin, marker_local=l2), Q


def _unc_dict(names, kids, cov):
    """The JSON form of an uncertainty that :func:`bench.uncertainty.joint_errors` reads."""
    out = {}
    for k, c in enumerate(kids):
        ev, vec = np.linalg.eigh(0.5 * (cov[k] + cov[k].T))
        ev, vec = np.maximum(ev[::-1], 0.0), vec[:, ::-1]
        out[names[c]] = {"sd_mm": np.sqrt(ev).tolist(), "directions": vec.T.tolist()}
    return {"joints": out}


@contextlib.contextmanager
def _no_noise_correction():
    """joint_uncertainty without the correction for the noise's part of the curvature: that part measured
    as zero, so the posterior precision is the data's Gauss-Newton curvature plus the prior (plain Laplace)."""
    real = unc_mod._noise_curvature

    def zero(pr, R, factors, sigma, V, seed, pairs):
        return np.zeros((V.shape[1], V.shape[1])), np.zeros(V.shape[1])

    unc_mod._noise_curvature = zero
    try:
        yield
    finally:
        unc_mod._noise_curvature = real


def run_case(case: Case, lm_cap: int = 1000, tight: bool = True) -> dict:
    """Both solvers on one case (see the module docstring); gtsam's own LM run for at most ``lm_cap``
    iterations (0: not at all), the LM loop to the end."""
    parent, origin, seg, local, obs, rot, root = _unpack(case)
    kw = case.kwargs
    ref = int(kw["ref_frame"])
    assert not kw.get("hold_along") and not kw.get("like_bones"), "the bench models the MAP path's priors only"
    iters, tol = int(kw.get("iterations", 30)), float(kw.get("tol", 1e-5))
    pr = calibrate._Problem(parent, seg, obs)
    out = {"name": case.name, "frames": obs.shape[0], "markers": int(pr.used.size), "segments": len(parent)}

    # ours: the MAP, then the uncertainty with and without the noise correction
    with peak_rss() as mem:
        t = time.perf_counter()
        res = calibrate.refine_skeleton(*case.args, **kw)
        out["ours_map_s"] = time.perf_counter() - t
    out["ours_map_mb"] = mem["mb"]
    out["ours_iter"] = res.n_iter
    t = time.perf_counter()
    u_ours = unc_mod.joint_uncertainty(parent, res.origin, seg, res.marker_local, obs, res.rot, res.root_pos, ref_frame=ref)
    out["ours_unc_s"] = time.perf_counter() - t
    with _no_noise_correction():
        t = time.perf_counter()
        u_plain = unc_mod.joint_uncertainty(parent, res.origin, seg, res.marker_local, obs, res.rot, res.root_pos,
                                            ref_frame=ref)
        out["ours_unc_plain_s"] = time.perf_counter() - t
    d_ours = pr.offsets(res.origin)

    # gtsam: the same start, the same priors, LM, then the marginals
    t = time.perf_counter()
    gm = GraphModel(parent, origin, seg, local, obs, rot, root, ref_frame=ref,
                    prior_weights=kw["prior_weights"], anchor=kw["anchor"])
    graph = gm.build()
    v0 = gm.values(root, rot, gm.d0, local)
    out["gtsam_build_s"] = time.perf_counter() - t
    out["factors"] = int(graph.size())
    out["variables"] = int(v0.size())
    n_marker = int(gm.seen[:, pr.used].sum())
    # one linearisation and one evaluation of the whole graph, from Python (the calls into the factors included)
    t = time.perf_counter()
    graph.linearize(v0)
    out["gtsam_lin_one_s"] = time.perf_counter() - t
    t = time.perf_counter()
    graph.error(v0)
    out["gtsam_err_one_s"] = time.perf_counter() - t
    sols = {}
    for how in ("gtsam LM", "gtsam loop"):
        if how == "gtsam LM" and lm_cap == 0:
            continue
        for k in gm.calls:
            gm.calls[k] = 0
        with peak_rss() as mem:
            t = time.perf_counter()
            if how == "gtsam LM":
                lm = gtsam.LevenbergMarquardtParams()
                lm.setMaxIterations(min(iters, lm_cap))
                lm.setRelativeErrorTol(tol)
                lm.setAbsoluteErrorTol(0.0)
                lm.setDiagonalDamping(True)
                lm.setlambdaInitial(1e-4)
                opt = gtsam.LevenbergMarquardtOptimizer(graph, v0, lm)
                sol = opt.optimize()
                n_it = int(opt.iterations())
            else:
                sol, n_it, t_solve = lm_loop(graph, v0, iters, tol)
                out[f"{how}_solve_s"] = t_solve
            out[f"{how}_s"] = time.perf_counter() - t
        out[f"{how}_mb"] = mem["mb"]
        out[f"{how}_iter"] = n_it
        # time inside the Python factors (marker factors counted; the priors' are a handful)
        out[f"{how}_py_s"] = gm.calls["t_lin"] + gm.calls["t_err"]
        out[f"{how}_linearisations"] = round(gm.calls["n_lin"] / n_marker)
        out[f"{how}_evaluations"] = round(gm.calls["n_err"] / n_marker)
        sols[how] = sol
    # the MAP compared below: gtsam's own LM when it ran to the end, else the loop's
    full = "gtsam LM" in sols and out["gtsam LM_iter"] < lm_cap
    sol = sols["gtsam LM" if full else "gtsam loop"]
    out["gtsam_map_from"] = "gtsam LM" if full else "gtsam loop"
    e_sol = graph.error(sol)
    pg, Rg, dg, lg = gm.read(sol)
    if "gtsam LM" in sols:
        J_a = pr.fk(*gm.read(sols["gtsam LM"]))[0][:, pr.kids]
        J_b = pr.fk(*gm.read(sols["gtsam loop"]))[0][:, pr.kids]
        out["lm_vs_loop_mm"] = float(np.sqrt(np.sum((J_a - J_b) ** 2, -1)).max())

    # both to convergence (tolerance 1e-12): do they reach the same optimum?
    if tight:
        kw_t = dict(kw, tol=1e-12, iterations=200)
        res_t = calibrate.refine_skeleton(*case.args, **kw_t)
        sol_t, it_t, _ = lm_loop(graph, v0, 200, 1e-12)
        Jo = pr.fk(res_t.root_pos, res_t.rot, pr.offsets(res_t.origin), res_t.marker_local)[0][:, pr.kids]
        Jg = pr.fk(*gm.read(sol_t))[0][:, pr.kids]
        out["tight_maps_max_mm"] = float(np.sqrt(np.sum((Jo - Jg) ** 2, -1)).max())
        out["tight_obj"] = (res_t.objective, 2.0 * graph.error(sol_t))
        out["tight_iter"] = (res_t.n_iter, it_t)

    # the MAPs: joints of every frame of the fit, against each other and the truth
    A = gm.A
    # ours' result turned back from its rest gauge (identity rotations at the reference frame) into the
    # refinement's (the reference frame's rotations as they start), where the prior's terms are stated
    Q0 = rot[ref]
    R_int = res.rot @ Q0[None]
    d_int = np.einsum("cji,cj->ci", Q0[np.maximum(parent, 0)], d_ours)
    l_int = res.marker_local.copy()
    ok = (seg >= 0) & np.isfinite(l_int).all(1)
    l_int[ok] = np.einsum("mji,mj->mi", Q0[seg[ok]], l_int[ok])
    out["ours_obj"] = objective(pr, A, gm.u0, res.root_pos, R_int, d_int, l_int)
    out["ours_obj_reported"] = res.objective
    out["gtsam_obj"] = objective(pr, A, gm.u0, pg, Rg, dg, lg)
    out["gtsam_obj_graph"] = 2.0 * e_sol
    out["start_obj"] = objective(pr, A, gm.u0, root, rot, gm.d0, local)
    J_ours = pr.fk(res.root_pos, res.rot, d_ours, res.marker_local)[0][:, pr.kids]
    J_gt = pr.fk(pg, Rg, dg, lg)[0][:, pr.kids]
    out["maps_rms_mm"] = float(np.sqrt(np.mean(np.sum((J_ours - J_gt) ** 2, -1))))
    out["maps_max_mm"] = float(np.sqrt(np.sum((J_ours - J_gt) ** 2, -1)).max())
    smap = segment_map(seg, case.truth)
    tr = case.truth
    pick = []
    for k, c in enumerate(pr.kids):
        pair = {smap.get(int(c), -1), smap.get(int(parent[c]), -2)}
        e = [i for i, ch in enumerate(tr.joint_child) if {int(ch), int(tr.parent[ch])} == pair]
        if len(e) == 1:
            pick.append((k, e[0]))
    if pick:
        T = tr.joints[case.frames][:, [e for _, e in pick]]
        ks = [k for k, _ in pick]
        for who, J in (("ours", J_ours), ("gtsam", J_gt)):
            err = np.sqrt(np.sum((J[:, ks] - T) ** 2, -1))
            ok = np.isfinite(err)
            out[f"{who}_truth_rms_mm"] = float(np.sqrt(np.mean(err[ok] ** 2)))

    # the uncertainty: gtsam's marginals at its MAP, the data's sigma from its residual (our dof)
    n_obs, dof = unc_mod._dof(pr)
    s2 = max(pr.cost(pg, Rg, dg, lg) / dof, 1e-12)
    out["noise_ours"], out["noise_gtsam"] = u_ours.noise_sd, float(np.sqrt(s2))
    prior_sd = u_ours.prior_sd
    with peak_rss() as mem:
        t = time.perf_counter()
        g2 = gm.build(sigma=float(np.sqrt(s2)), priors="uncertainty", prior_sd=prior_sd, l_at=lg)
        marg = gtsam.Marginals(g2, sol)
        K = len(pr.kids)
        cov_g = np.zeros((K, 3, 3))
        for k, c in enumerate(pr.kids):
            ms = [int(m) for m in pr.used if pr.seg[m] == c]
            Ac, _ = unc_mod._joint_operator(pr, lg, c)
            J = np.hstack([Ac[:, pr.gl[m] : pr.gl[m] + 3] for m in ms])
            keys = gtsam.KeyVector([gm.kL(m) for m in ms])
            Sig = marg.jointMarginalCovariance(keys).fullMatrix()
            cov_g[k] = J @ Sig @ J.T
        out["gtsam_unc_s"] = time.perf_counter() - t
    out["gtsam_unc_mb"] = mem["mb"]
    # into the lab's axes at the rest frame, as ours reports them
    skel_g, Q = _to_skeleton(case.start, parent, origin, seg, pg, Rg, dg, lg, ref)
    Qc = Q[np.array(pr.kids)]
    cov_g = Qc @ cov_g @ np.swapaxes(Qc, 1, 2)

    def sds(cov):
        return np.sqrt(np.maximum(np.linalg.eigvalsh(cov)[:, ::-1], 0.0))

    sd_g, sd_o, sd_p = sds(cov_g), u_ours.sd, u_plain.sd
    out["sd"] = {"gtsam": sd_g, "ours": sd_o, "plain": sd_p, "prior_sd": prior_sd}
    # the covariances compared whole: the largest relative difference of sd along any direction
    out["plain_vs_gtsam"] = _cov_gap(u_plain.cov, cov_g)
    out["ours_vs_gtsam"] = _cov_gap(u_ours.cov, cov_g)

    # coverage of the truth (joints whose child has 3+ markers), each uncertainty at its own MAP
    skel_o = replace(case.start, origin=res.origin, marker_local=res.marker_local)
    names = case.start.names
    out["coverage"] = {
        "ours": joint_errors(skel_o, tr, _unc_dict(names, u_ours.kids, u_ours.cov)),
        "plain": joint_errors(skel_o, tr, _unc_dict(names, u_plain.kids, u_plain.cov)),
        "gtsam": joint_errors(skel_g, tr, _unc_dict(names, np.array(pr.kids), cov_g)),
    }
    return out


def _cov_gap(C1: np.ndarray, C2: np.ndarray) -> float:
    """The largest relative gap between two covariances over the joints: max |log(sd1 / sd2)| along the
    generalised eigen-directions (0 for equal covariances)."""
    gaps = []
    for a, b in zip(C1, C2):
        L = np.linalg.cholesky(b + 1e-12 * np.trace(b) * np.eye(3))
        Li = np.linalg.inv(L)
        ev = np.linalg.eigvalsh(Li @ a @ Li.T)
        gaps.append(float(np.abs(0.5 * np.log(np.maximum(ev, 1e-300))).max()))
    return float(np.expm1(max(gaps)))


# --------------------------------------------------------------------------------------------------
# the report


def _cases(args):
    """(name, take factory, refine frames, gtsam LM cap) of every case asked for."""
    out = []
    for s in _seeds(args.chain_seeds):
        out.append((f"hinge chain <4-3-3-3> seed {s}", lambda s=s: hinge_chain((4, 3, 3, 3), 1200,
                    rng=np.random.default_rng(s), noise=1.0), args.frames, args.lm_cap))
    if args.large:
        out.append((f"hinge chain <4-3-3-3> seed 1, refine_frames={args.large}",
                    # the refinement fits at most a quarter of a take's frames
                    lambda: hinge_chain((4, 3, 3, 3), 4 * args.large, rng=np.random.default_rng(1), noise=1.0),
                    args.large, 0))
    for s in _seeds(args.human_seeds):
        out.append((f"human ROM seed {s}", lambda s=s: make(active_rom(seed=s, frames=1200)), args.frames,
                    args.human_lm_cap))
    return out


def _seeds(text: str) -> list[int]:
    if not text:
        return []
    a, _, b = text.partition("-")
    return list(range(int(a), int(b or a) + 1))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--chain-seeds", default="1-4")
    ap.add_argument("--human-seeds", default="1")
    ap.add_argument("--frames", type=int, default=300, help="frames of the refinement (the rigid stage's)")
    ap.add_argument("--large", type=int, default=1200, help="a chain refined on this many frames too (0: not)")
    ap.add_argument("--lm-cap", type=int, default=1000, help="iterations of gtsam's own LM on the chains")
    ap.add_argument("--human-lm-cap", type=int, default=1,
                    help="iterations of gtsam's own LM on the human (each costs tens of seconds: see the notes)")
    ap.add_argument("--callback-values", default="0,2000,8000",
                    help="the cost of a Python factor in gtsam's optimizer, beside these many other values")
    args = ap.parse_args(argv)
    print("## Factor graph (gtsam) against our solver\n")
    if gtsam is None:
        print("gtsam is not installed (`pip install gtsam==4.3.0`; it is no dependency of mocapskel): nothing measured.")
        return
    from importlib.metadata import version

    print(f"Machine: {machine()}; gtsam {version('gtsam')} (its wheel links no TBB: one thread); "
          f"MOCAPSKEL_THREADS={os.environ['MOCAPSKEL_THREADS']}, OMP_NUM_THREADS={os.environ['OMP_NUM_THREADS']}.\n")
    from threadpoolctl import threadpool_limits

    rows = []
    with threadpool_limits(limits=1, user_api="blas"):
        for name, factory, frames, cap in _cases(args):
            take = factory()
            case = capture(take.markers, take.truth, name, refine_frames=frames)
            try:
                rows.append(run_case(case, lm_cap=cap, tight=True))
            except RuntimeError as err:  # said, and the next case
                print(f"- {name}: failed ({str(err).strip().splitlines()[0][:200]})\n")
            print(f"<!-- done: {name} -->", file=sys.stderr, flush=True)
    if rows:
        _report(rows)
    callback_cost([int(x) for x in args.callback_values.split(",") if x])


def callback_cost(extra_values: list[int], n_factors: int = 1000) -> None:
    """What a Python factor costs inside gtsam's optimizer: ``n_factors`` trivial ``CustomFactor`` s (a prior on
    one Point3 each) beside more values (each with a built-in prior), one linearisation called from Python
    against one Gauss-Newton iteration of gtsam's optimizer."""
    if not extra_values:
        return

    def err(this, v, H):
        x = v.atPoint3(this.keys()[0])
        if H is not None:
            H[0] = np.eye(3)
        return x - 1.0

    print(f"\n### {n_factors} trivial Python factors beside other values: one linearisation from Python against"
          " one Gauss-Newton iteration of gtsam's optimizer\n")
    print("| values | linearise from Python (ms) | one optimizer iteration (ms) |")
    print("|---:|---:|---:|")
    for extra in extra_values:
        g, v = gtsam.NonlinearFactorGraph(), gtsam.Values()
        unit = gtsam.noiseModel.Unit.Create(3)
        for i in range(n_factors):
            g.add(gtsam.CustomFactor(unit, [i], err))
            v.insert(i, np.zeros(3))
        for j in range(extra):
            k = n_factors + j
            v.insert(k, np.zeros(3))
            g.add(gtsam.PriorFactorPoint3(k, np.zeros(3), unit))
        t = time.perf_counter()
        g.linearize(v)
        a = time.perf_counter() - t
        p = gtsam.GaussNewtonParams()
        p.setMaxIterations(1)
        opt = gtsam.GaussNewtonOptimizer(g, v, p)
        t = time.perf_counter()
        opt.iterate()
        b = time.perf_counter() - t
        print(f"| {n_factors + extra} | {a * 1e3:.0f} | {b * 1e3:.0f} |")


def _report(rows: list[dict]) -> None:
    print("### Speed (one thread, seconds; peak memory over the start, MB)\n")
    print("| case | frames | factors / variables | ours MAP | gtsam LM | of which in the Python factors | gtsam LM per iteration |"
          " LM loop on gtsam | of which linear solves | ours uncertainty (plain) | gtsam marginals | peak MB ours / gtsam LM / loop |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        lm = r.get("gtsam LM_s")
        lm_txt = "—" if lm is None else (f"{lm:.1f} ({r['gtsam LM_iter']} it.)" if r["gtsam_map_from"] == "gtsam LM"
                                         else f"not run to the end ({r['gtsam LM_iter']} it.: {lm:.1f})")
        per = "—" if lm is None else f"{lm / max(r['gtsam LM_iter'], 1):.2f}"
        py = "—" if lm is None else f"{r['gtsam LM_py_s']:.2f}"
        print(f"| {r['name']} | {r['frames']} | {r['factors']} / {r['variables']} | {r['ours_map_s']:.2f} ({r['ours_iter']} it.) |"
              f" {lm_txt} | {py} | {per} | {r['gtsam loop_s']:.2f} ({r['gtsam loop_iter']} it.) |"
              f" {r['gtsam loop_solve_s']:.2f} | {r['ours_unc_s']:.2f} ({r['ours_unc_plain_s']:.2f}) | {r['gtsam_unc_s']:.2f} |"
              f" {r['ours_map_mb']:.0f} / {r.get('gtsam LM_mb', float('nan')):.0f} / {r['gtsam loop_mb']:.0f} |")
    print("\n### The MAP (the refinement's tolerance 1e-5, then both to 1e-12)\n")
    print("| case | objective start | ours | gtsam | joints ours vs gtsam, max mm | at 1e-12: objectives | at 1e-12: joints max mm |"
          " iterations at 1e-12 | joints vs truth rms mm ours / gtsam |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        to, tg = r["tight_obj"]
        print(f"| {r['name']} | {r['start_obj']:.2f} | {r['ours_obj']:.4f} | {r['gtsam_obj']:.4f} ({r['gtsam_map_from']}) |"
              f" {r['maps_max_mm']:.3g} | {to:.6f} / {tg:.6f} | {r['tight_maps_max_mm']:.2g} | {r['tight_iter'][0]} / {r['tight_iter'][1]} |"
              f" {r.get('ours_truth_rms_mm', float('nan')):.2f} / {r.get('gtsam_truth_rms_mm', float('nan')):.2f} |")
    print("\n### The uncertainty (sd along each joint's principal axes, mm: medians over the joints)\n")
    print("| case | noise mm ours / gtsam | prior sd | ours (noise corrected) | ours plain | gtsam marginals |"
          " largest gap ours plain vs gtsam | ours vs gtsam |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        sd = r["sd"]

        def f(a):
            return " / ".join(f"{x:.3g}" for x in np.median(a, 0))

        print(f"| {r['name']} | {r['noise_ours']:.4f} / {r['noise_gtsam']:.4f} | {np.median(sd['prior_sd']):.0f} |"
              f" {f(sd['ours'])} | {f(sd['plain'])} | {f(sd['gtsam'])} | {r['plain_vs_gtsam']:.1e} | {r['ours_vs_gtsam']:.3g} |")
    print("\n### Coverage of the truth by the 95 % region (joints whose child has 3+ markers, pooled over seeds)\n")
    print("| takes | joints | ours (noise corrected) | ours plain | gtsam marginals | median error mm | median 95 % radius mm ours / plain / gtsam |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    groups: dict[str, list] = {}
    for r in rows:
        key = r["name"].split(" seed")[0] + (f", {r['frames']} frames" if "refine_frames" in r["name"] else "")
        groups.setdefault(key, []).append(r)
    for key, rs in groups.items():
        cov = {w: np.array([e for r in rs for e in r["coverage"][w]]).reshape(-1, 3) for w in ("ours", "plain", "gtsam")}
        n = len(cov["ours"])
        if not n:
            continue
        inside = [f"{np.mean(cov[w][:, 0] <= CHI2_3_95):.0%}" for w in ("ours", "plain", "gtsam")]
        radius = " / ".join(f"{np.median(cov[w][:, 2]):.3g}" for w in ("ours", "plain", "gtsam"))
        print(f"| {key} ({len(rs)} seeds) | {n} | {' | '.join(inside)} | {np.median(cov['ours'][:, 1]):.3g} | {radius} |")


if __name__ == "__main__":
    main()
