"""The skeleton model built independently in a factor-graph library (gtsam, optional) reaches our MAP and
our plain Laplace covariance: a check of calibrate.refine_skeleton and of the uncertainty's curvature."""
import numpy as np
import pytest

gtsam = pytest.importorskip("gtsam")

from bench import factor_graph as fg  # noqa: E402
from mocapskel.solvers.model import calibrate  # noqa: E402
from mocapskel.solvers.model import uncertainty as unc_mod  # noqa: E402
from mocapskel.synth.chains import hang_chain  # noqa: E402

LINK = 300.0


@pytest.fixture(scope="module")
def solved():
    take = hang_chain((4, 3, 3), 240, rng=np.random.default_rng(7), link_length=LINK, noise=0.5)
    case = fg.capture(take.markers, take.truth, "chain", refine_frames=60)
    parent, origin, seg, local, obs, rot, root = fg._unpack(case)
    kw = dict(case.kwargs, tol=1e-14, iterations=300)
    ours = calibrate.refine_skeleton(*case.args, **kw)
    gm = fg.GraphModel(parent, origin, seg, local, obs, rot, root, ref_frame=kw["ref_frame"],
                       prior_weights=kw["prior_weights"], anchor=kw["anchor"])
    graph = gm.build()
    lm = gtsam.LevenbergMarquardtParams()
    lm.setMaxIterations(300)
    lm.setRelativeErrorTol(1e-14)
    lm.setAbsoluteErrorTol(0.0)
    lm.setDiagonalDamping(True)
    sol = gtsam.LevenbergMarquardtOptimizer(graph, gm.values(root, rot, gm.d0, local), lm).optimize()
    return case, ours, gm, graph, sol


def test_gtsam_reaches_our_map(solved):
    case, ours, gm, graph, sol = solved
    parent = np.asarray(case.args[0])
    pr = gm.pr
    J_ours = pr.fk(ours.root_pos, ours.rot, pr.offsets(ours.origin), ours.marker_local)[0][:, pr.kids]
    J_gt = pr.fk(*gm.read(sol))[0][:, pr.kids]
    assert np.abs(J_ours - J_gt).max() < 1e-6 * LINK
    # the same objective: gtsam's error is half our cost (unit noise, sigma 1 / sqrt(weight) priors)
    assert abs(2.0 * graph.error(sol) - ours.objective) < 1e-8 * ours.objective


def test_gtsam_marginals_match_our_plain_laplace(solved):
    """At the MAP, gtsam's marginal covariance of each joint relative to its child's markers equals the
    covariance of joint_uncertainty without its noise correction (Gauss-Newton curvature plus the prior)."""
    case, ours, gm, graph, sol = solved
    parent, origin, seg, local, obs, rot, root = fg._unpack(case)
    ref = case.kwargs["ref_frame"]
    with fg._no_noise_correction():
        u = unc_mod.joint_uncertainty(parent, ours.origin, seg, ours.marker_local, obs, ours.rot, ours.root_pos,
                                      ref_frame=ref)
    pr = gm.pr
    p, R, d, l = gm.read(sol)
    s2 = pr.cost(p, R, d, l) / unc_mod._dof(pr)[1]
    assert abs(np.sqrt(s2) - u.noise_sd) < 1e-6 * u.noise_sd
    marg = gtsam.Marginals(gm.build(sigma=float(np.sqrt(s2)), priors="uncertainty", prior_sd=u.prior_sd, l_at=l), sol)
    for k, c in enumerate(pr.kids):
        ms = [int(m) for m in pr.used if pr.seg[m] == c]
        Ac, _ = unc_mod._joint_operator(pr, l, c)
        J = np.hstack([Ac[:, pr.gl[m] : pr.gl[m] + 3] for m in ms])
        S = marg.jointMarginalCovariance(gtsam.KeyVector([gm.kL(m) for m in ms])).fullMatrix()
        Q = R[ref, c]  # gtsam's child frame at the reference frame: into the rest frame's lab axes, as ours
        cov = Q @ J @ S @ J.T @ Q.T
        assert fg._cov_gap(u.cov[k : k + 1], cov[None]) < 1e-4
