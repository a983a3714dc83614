import numpy as np
import pytest

from mocapskel import pipeline
from mocapskel.errors import DataError
from mocapskel.solvers.grouping import distances, grouping
from mocapskel.stages import segment
from mocapskel.synth.chains import hang_chain


def same_partition(a, b) -> bool:
    pairs = set(zip(a.tolist(), b.tolist()))
    return len(pairs) == len(set(a.tolist())) == len(set(b.tolist()))


@pytest.mark.parametrize("counts", [(4, 3, 3), (4, 3, 3, 4, 3), (3, 2, 2, 2, 2), (3, 1, 2, 2, 2, 2)])
@pytest.mark.parametrize("seed", [0, 1])
def test_chain_segments_and_tree_found_without_being_told(counts, seed):
    tk = hang_chain(counts, 200, rng=np.random.default_rng(seed))
    topo = pipeline.run_until(tk.markers, "topology").artifact
    seg = topo.segments
    assert seg.n_segments == len(counts)
    assert same_partition(seg.group, tk.truth.marker_segment)
    # map found segments to true ones and compare the undirected edge sets
    to_true = {int(g): int(t) for g, t in zip(seg.group, tk.truth.marker_segment)}
    found = {frozenset((to_true[a], to_true[b])) for a, b in topo.edges}
    truth = {frozenset((int(tk.truth.parent[c]), int(c))) for c in tk.truth.joint_child}
    assert found == truth


def test_given_number_of_segments_is_used(linkage):
    seg = pipeline.run_until(linkage.markers, "segment", {"segment": segment.Params(n_segments=3)}).artifact
    assert seg.n_segments == 3
    assert same_partition(seg.group, linkage.truth.marker_segment)


def test_one_rigid_body_is_refused(linkage):
    from dataclasses import replace

    m = linkage.markers
    rigid = replace(m, points=m.points[:, :3])  # the three markers of one rod
    with pytest.raises(DataError, match="one rigid body"):
        pipeline.run_until(rigid, "segment")


# --------------------------------------------------------------------------- vectorised kernels against plain references


def test_distance_std_is_bit_for_bit_the_plain_formula():
    rng = np.random.default_rng(5)
    for M in (2, 3, 9, 30):
        pts = rng.normal(size=(120, M, 3)) * 300.0
        pts[rng.random((120, M)) < 0.2] = np.nan
        pts[3, 0, 1] = np.inf
        pts[:, M - 1][5:] = np.nan  # seen once: std NaN
        with np.errstate(invalid="ignore"):
            d = np.linalg.norm(pts[:, :, None, :] - pts[:, None, :, :], axis=-1)
        ok = np.isfinite(d)
        cnt = ok.sum(axis=0)
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = np.where(ok, d, 0.0).sum(axis=0) / cnt
            std = np.sqrt((np.where(ok, d - mean, 0.0) ** 2).sum(axis=0) / cnt)
        std[cnt < 2] = np.nan
        got, got_cnt = distances.distance_std(pts)
        assert np.array_equal(got_cnt, cnt) and got_cnt.dtype == cnt.dtype
        if M > 2:  # two markers: one pair, whose sum numpy may add pairwise instead of in order
            assert np.array_equal(got, std, equal_nan=True)
        np.testing.assert_allclose(got, std, rtol=1e-12, equal_nan=True)


def _networkx_tree(C: np.ndarray, size: dict[int, int]):
    """The tree as the stage built it with networkx: Kruskal MST, centre root, BFS edges."""
    nx = pytest.importorskip("networkx")
    S = C.shape[0]
    G = nx.Graph()
    G.add_nodes_from(range(S))
    for a in range(S):
        for b in range(a + 1, S):
            if np.isfinite(C[a, b]):
                G.add_edge(a, b, weight=float(C[a, b]))
    if not nx.is_connected(G):
        return None
    T = nx.minimum_spanning_tree(G, weight="weight", algorithm="kruskal")
    ecc = nx.eccentricity(T)
    cands = [n for n, e in ecc.items() if e == min(ecc.values())]
    dist = {n: sum(nx.single_source_shortest_path_length(T, n).values()) for n in cands}
    root = min(cands, key=lambda n: (dist[n], -size.get(n, 0), n))
    return root, [tuple(e) for e in nx.bfs_edges(T, root)]


@pytest.mark.parametrize("seed", range(30))
def test_tree_is_networkx_kruskal_centre_and_bfs(seed):
    from mocapskel.stages import topology

    rng = np.random.default_rng(seed)
    S = int(rng.integers(2, 16))
    C = np.round(rng.uniform(0, 5, (S, S)), 0 if seed % 2 else 3)  # integer costs: many ties
    C = np.triu(C, 1)
    C = C + C.T
    C[rng.random((S, S)) < 0.3 * (seed % 3)] = np.inf
    C = np.minimum(C, C.T)
    np.fill_diagonal(C, np.inf)
    size = {s: int(rng.integers(1, 5)) for s in range(S)}
    want = _networkx_tree(C, size)
    tree = topology.minimum_spanning_tree(S, C)
    if want is None:
        assert tree is None
        return
    root = topology.tree_centre(S, tree, size)
    assert root == want[0]
    assert topology._bfs(topology._neighbours(S, tree), root)[0] == want[1]


def test_topology_of_a_long_take_reads_each_frame_once(linkage):
    """Per-frame visibility of the segments (one product) gives the same tree and costs as counting per segment."""
    from dataclasses import replace

    from mocapskel.stages import topology

    m = linkage.markers
    pts = np.concatenate([m.points] * 5)  # 12,000 frames
    pts[np.random.default_rng(2).random(pts.shape[:2]) < 0.05] = np.nan
    seg = segment.run(replace(m, points=pts))
    topo = topology.run(seg)
    assert seg.n_segments == 3 and len(topo.edges) == 2
    frames = topology.subsample(pts, topology.Params().n_frames)
    assert np.array_equal(frames, topology.subsample(pts, topology.Params().n_frames, visible=np.isfinite(pts).all(-1)))
    seen = np.stack([np.isfinite(pts[:, seg.members(s)]).all(-1).sum(1) for s in range(seg.n_segments)], axis=1)
    a, b = topo.edges[0]
    fr = topology.pair_frames(seen[:, a], seen[:, b], frames, topology.Params().n_frames)
    from mocapskel.solvers.grouping.pair_cost import pair_cost

    assert topo.cost[0] == pair_cost(pts[fr][:, seg.members(a)], pts[fr][:, seg.members(b)], alpha=topo.info["alpha"])


def test_average_linkage_heights_match_scipy():
    from scipy.cluster.hierarchy import fcluster, linkage
    from scipy.spatial.distance import squareform

    from mocapskel.solvers.grouping.distances import average_linkage_heights, rigid_groups

    rng = np.random.default_rng(3)
    for M in (2, 3, 7, 30, 90):
        X = rng.normal(size=(M, 4)) * rng.uniform(0.1, 10, size=(M, 1))
        D = np.linalg.norm(X[:, None] - X[None], axis=-1)
        Z = linkage(squareform(D, checks=False), method="average")
        np.testing.assert_allclose(average_linkage_heights(D), np.sort(Z[:, 2]), rtol=1e-12)
        for t in np.quantile(Z[:, 2], [0.1, 0.5, 0.9]):
            assert rigid_groups(D, t).max() + 1 == fcluster(Z, t=t, criterion="distance").max()


def test_merge_still_groups_joins_only_groups_that_hardly_move_against_each_other() -> None:
    from mocapskel.solvers.grouping.distances import merge_still_groups

    # four groups: 0 and 1 vary against each other by 2 mm, 2 against both by 20 mm, 3 alone by 40 mm
    lab = np.array([0, 0, 1, 1, 1, 2, 2, 3])
    G = np.array([[0.3, 2.0, 20.0, 40.0], [2.0, 0.3, 20.0, 40.0], [20.0, 20.0, 0.3, 40.0], [40.0, 40.0, 40.0, 0.0]])
    std = G[lab][:, lab]
    np.fill_diagonal(std, 0.0)
    assert merge_still_groups(std, lab, 3.0).tolist() == [0, 0, 0, 0, 0, 1, 1, 2]
    assert merge_still_groups(std, lab, 1.0).tolist() == lab.tolist()
    assert merge_still_groups(std, lab, 25.0).tolist() == [0, 0, 0, 0, 0, 0, 0, 1]


def test_absorb_lone_markers_by_the_farthest_member_when_asked():
    from mocapskel.solvers.grouping.grouping import absorb_lone_markers

    # marker 4 alone: against group 0 (markers 0, 1) it varies by 2 and 9 mm, against group 1
    # (markers 2, 3) by 30 and 40 mm
    std = np.full((5, 5), 50.0)
    np.fill_diagonal(std, 0.0)
    std[0, 1] = std[1, 0] = std[2, 3] = std[3, 2] = 0.5
    std[4, [0, 1, 2, 3]] = std[[0, 1, 2, 3], 4] = [2.0, 9.0, 30.0, 40.0]
    mean_d = np.full((5, 5), 100.0)
    lab = np.array([0, 0, 1, 1, 2])
    assert absorb_lone_markers(std, mean_d, lab, 6.0, 200.0)[0].tolist() == [0, 0, 1, 1, 0]  # mean 5.5
    assert absorb_lone_markers(std, mean_d, lab, 6.0, 200.0, nearest=True)[0].tolist() == lab.tolist()  # max 9
    assert absorb_lone_markers(std, mean_d, lab, 10.0, 200.0, nearest=True)[0].tolist() == [0, 0, 1, 1, 0]
    assert absorb_lone_markers(std, mean_d, lab, 10.0, 50.0)[0].tolist() == lab.tolist()  # out of reach


def test_walking_thighs_join_the_pelvis_not_each_other():
    """Realistic CMU marker set, walking: both hips flex about one mediolateral axis, so the two thighs
    "join" cheaply on it, and the hip sits far from a two-marker thigh's markers (mid-thigh and knee)
    while a hanging arm's elbow is near it. Each thigh group must hang on the pelvis group (the truth's
    parent of both thighs), as the generator's tree has it."""
    from mocapskel.synth.presets import make, realistic

    take = make(realistic(seed=1, frames=600, motion="walk", markerset="cmu41"))
    topo = pipeline.run_until(take.markers, "topology").artifact
    seg, truth = topo.segments, take.truth
    names = list(truth.segment_names)

    def true_segment(s: int) -> str:
        ids = [int(truth.marker_segment[i]) for i in seg.members(s)]
        return names[max(set(ids), key=ids.count)]

    edges = {frozenset((true_segment(a), true_segment(b))) for a, b in topo.edges.tolist()}
    assert frozenset(("Pelvis", "LThigh")) in edges and frozenset(("Pelvis", "RThigh")) in edges
    assert frozenset(("LThigh", "RThigh")) not in edges


def test_walking_head_hangs_on_the_trunk_not_on_an_arm(tmp_path):
    """Realistic CMU marker set, walking: the head moves with the trunk, so a two-marker upper arm given
    its shoulder (its cheapest joint, with the trunk) as an extra point "joined" the head on that point
    by dilution alone (the point's near-zero variance lowered the mean cost: 7.1 against the trunk's
    7.5). The head group must be a leaf on the trunk, as the generator's tree has it."""
    from mocapskel.synth.presets import make, realistic

    from dataclasses import replace

    from mocapskel.io.markers import write_markers

    take = make(realistic(seed=1, frames=600, motion="walk", markerset="cmu41"))
    path = tmp_path / "walk.c3d"  # as a user has it: a C3D file (single-precision coordinates)
    write_markers(path, replace(take.markers, source=path.name))
    topo = pipeline.run_until(path, "topology", pipeline.make_params(up="z", units="mm")).artifact
    seg, truth = topo.segments, take.truth
    names = list(truth.segment_names)

    def true_segment(s: int) -> str:
        ids = [int(truth.marker_segment[i]) for i in seg.members(s)]
        return names[max(set(ids), key=ids.count)]

    head = [s for s in range(seg.n_segments) if true_segment(s) == "Head"]
    assert len(head) == 1
    nbrs = [b if a == head[0] else a for a, b in topo.edges.tolist() if head[0] in (a, b)]
    assert [true_segment(s) for s in nbrs] == ["Torso"]
    # ... and no group with a marker of an upper arm (a group of LSHO and LUPA counts as the torso above)
    assert not {names[int(truth.marker_segment[i])] for i in seg.members(nbrs[0])} & {"LUpperArm", "RUpperArm"}


def test_own_floor_is_the_radial_variance_of_a_segments_scatter():
    """A segment's floor is the variance, over frames, of a marker's distance to a point fixed in the
    segment that its scatter alone gives: checked against that variance measured directly (markers
    scattering isotropically by 3 mm about a rigid body that turns and moves; the point fixed in the
    true body frame)."""
    from mocapskel.stages import topology
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(5)
    K, n, sd = 400, 6, 3.0
    body = rng.normal(0.0, 80.0, (n, 3))
    R = Rotation.random(K, random_state=7).as_matrix()
    t = rng.normal(0.0, 500.0, (K, 3))
    P = np.einsum("kij,nj->kni", R, body) + t[:, None] + rng.normal(0.0, sd, (K, n, 3))
    joint = np.einsum("kij,j->ki", R, np.array([150.0, 0.0, 40.0])) + t
    direct = np.var(np.linalg.norm(P - joint[:, None], axis=2), axis=0).mean()
    floor = topology.own_floor(P, [np.arange(n), np.array([0])])
    # the rigid fit takes up some of the scatter (6 of 3n degrees of freedom per frame)
    assert floor[0] == pytest.approx(direct * (1 - 6 / (3 * n)), rel=0.1)
    assert floor[1] == floor[0]  # a one-marker segment gets the least floor of the others


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_walking_upper_arms_hang_on_the_trunk_not_on_each_other(seed):
    """Generated human walking: both upper arms swing about one mediolateral axis through both shoulders,
    so each arm's joint with the other (on that axis, at the other's shoulder) is as cheap as with the
    trunk, whose lumbar joint the walk hardly moves: pelvis and torso are one group that is not quite
    rigid, and its scatter raises its every cost. Both upper arms must hang on the trunk group."""
    from mocapskel.synth.presets import Recipe, make

    take = make(Recipe(kind="human", frames=600, noise_mm=1.0, soft_tissue_mm=2.0, gaps_per_marker_per_minute=4.0,
                       seed=seed, motion="walk"))
    topo = pipeline.run_until(take.markers, "topology").artifact
    seg = topo.segments
    codes = [{seg.markers.labels[m][:4] for m in seg.members(s)} for s in range(seg.n_segments)]
    arms = [next(s for s in range(seg.n_segments) if codes[s] == {c}) for c in ("LUPA", "RUPA")]
    for arm in arms:
        nbrs = [b if a == arm else a for a, b in topo.edges.tolist() if arm in (a, b)]
        assert any("TRSO" in codes[s] for s in nbrs), [codes[s] for s in nbrs]
        assert not any(codes[s] & {"LUPA", "RUPA"} for s in nbrs)


def test_a_lone_marker_takes_no_partner_that_is_far_more_rigid_with_its_own_group():
    """A lone thigh marker (4) and a group of four pelvis markers (0-3): a pelvis marker whose distance to
    the thigh marker varies 8 mm against 2 mm to its own group is the pelvis's, not a marker on the hip's
    axis; one that varies 3 mm to both sides is (a knee or elbow marker), and pairs."""
    from mocapskel.solvers.grouping.grouping import PARTNER_RATIO, pair_lone_markers

    M = 5
    mean_d = np.full((M, M), 150.0)
    lab = np.array([0, 0, 0, 0, 1])
    std = np.full((M, M), 30.0)
    std[:4, :4] = 2.0
    std[3, 4] = std[4, 3] = 8.0  # within tau_join, but four times its std to its own group
    got, moves = pair_lone_markers(std, mean_d, lab, tau_join=10.0, tau_free=1.0, reach=500.0)
    assert 8.0 > PARTNER_RATIO * 2.0
    assert got.tolist() == [0, 0, 0, 0, 1] and moves == []  # left alone: a segment of one marker
    std[3, :3] = std[:3, 3] = 3.0  # now on an axis: 3 mm to its group, 3 mm to the lone marker
    std[3, 4] = std[4, 3] = 3.0
    got, moves = pair_lone_markers(std, mean_d, lab, tau_join=10.0, tau_free=1.0, reach=500.0)
    assert got.tolist() == [0, 0, 0, 1, 1] and moves == [(3, "paired")]


def test_a_lone_marker_is_absorbed_by_the_group_nearest_in_space():
    """Skin on a body is on it: a lone marker (4) 150 mm from one group (0, 1) and 500 mm from another
    (2, 3) that it varies less against joins the near one, or none."""
    from mocapskel.solvers.grouping.grouping import absorb_lone_markers

    M = 5
    mean_d = np.full((M, M), 150.0)
    mean_d[4, 2:4] = mean_d[2:4, 4] = 500.0
    lab = np.array([0, 0, 1, 1, 2])
    std = np.full((M, M), 2.0)
    std[4, :2] = std[:2, 4] = 5.0
    std[4, 2:4] = std[2:4, 4] = 3.0
    assert absorb_lone_markers(std, mean_d, lab, 6.0, 600.0)[0].tolist() == [0, 0, 1, 1, 0]
    assert absorb_lone_markers(std, mean_d, lab, 4.0, 600.0)[0].tolist() == [0, 0, 1, 1, 2]  # not the far one


def _on_joint_case(between: float, far: float = 1.0):
    """Markers 0-2 (group A), 3-5 (group B) and 6 alone; 6's distance stds: 3 mm to A, 4 mm to B; A to B
    ``between``; mean distances: 6 is 150 mm from A and 170 from B, A and B 300 mm apart (``far`` scales 6's)."""
    std = np.full((7, 7), 1.0)
    std[np.ix_([0, 1, 2], [3, 4, 5])] = std[np.ix_([3, 4, 5], [0, 1, 2])] = between
    std[6, :3] = std[:3, 6] = 3.0
    std[6, 3:6] = std[3:6, 6] = 4.0
    np.fill_diagonal(std, 0.0)
    d = np.full((7, 7), 50.0)
    d[np.ix_([0, 1, 2], [3, 4, 5])] = d[np.ix_([3, 4, 5], [0, 1, 2])] = 300.0
    d[6, :3] = d[:3, 6] = 150.0 * far
    d[6, 3:6] = d[3:6, 6] = 170.0 * far
    np.fill_diagonal(d, 0.0)
    return std, d, np.array([0, 0, 0, 1, 1, 1, 2])


def test_a_lone_marker_on_the_joint_of_two_groups_joins_the_nearer_in_motion():
    std, d, lab = _on_joint_case(between=30.0)
    new, moves = grouping.join_markers_on_joints(std, d, lab)
    assert new.tolist() == [0, 0, 0, 1, 1, 1, 0] and moves == [(6, "on a joint")]
    # the groups hardly move against each other: its distances say nothing of a joint
    assert grouping.join_markers_on_joints(*_on_joint_case(between=10.0))[0].tolist() == lab.tolist()
    # not between them: far from both, any marker's distances vary little
    assert grouping.join_markers_on_joints(*_on_joint_case(between=30.0, far=3.0))[0].tolist() == lab.tolist()


def test_real_epicondyle_between_arm_and_forearm_clusters_joins_the_arm():
    """A wheelchair racer's right lateral epicondyle (0.16 of the arm-forearm distance std against either) was a
    one-marker segment between the arm's and the forearm's clusters, joined to both."""
    from pathlib import Path

    src = Path(__file__).resolve().parents[2] / "shared" / "realdata" / "kineticstoolkit" / "racing_full.c3d"
    if not src.is_file():
        pytest.skip(f"REAL DATA NOT FOUND at {src.parent.parent} — the real on-joint marker test did NOT run")
    seg = pipeline.run_until(src, "segment").artifact
    g = {lab: int(seg.group[i]) for i, lab in enumerate(seg.markers.labels)}
    assert g["LateralEpicondyleR"] == g["ArmR1"] == g["ArmR2"] == g["ArmR3"]
    assert ["LateralEpicondyleR", "on a joint"] in [list(m) for m in seg.info["moved"]]


def _group_and_marker(path_in_frame: np.ndarray, seed: int, noise: float = 1.0) -> np.ndarray:
    """(K, 4, 3) points: a rigid group of three markers moving at random, and a fourth marker whose place
    in the group's frame follows ``path_in_frame`` (K, 3); ``noise`` mm on every marker."""
    from mocapskel.solvers.rotations import rotvec_to_matrix

    rng = np.random.default_rng(seed)
    K = len(path_in_frame)
    shape = np.array([[0.0, 0.0, 0.0], [120.0, 0.0, 0.0], [40.0, 90.0, 0.0]])
    R = rotvec_to_matrix(rng.normal(0, 0.6, (K, 3)))
    t = rng.normal(0, 300, (K, 3))
    local = np.concatenate([np.broadcast_to(shape, (K, 3, 3)), path_in_frame[:, None]], axis=1)
    return np.einsum("kij,knj->kni", R, local) + t[:, None] + rng.normal(0, noise, (K, 4, 3))


def test_a_lone_marker_that_turns_about_a_point_of_its_group_is_told_from_skin_on_it():
    """A hand's marker about the wrist: its distances to the wrist's markers hardly change, but in their
    frame it runs over a sphere about one point. Turning 25 or 35 degrees either way about a point 90 mm
    from it, it is a body of its own. Moved as much but off any sphere (skin sliding), it is not; nor is one
    that turns half the take about that point and half about one 40 mm from it (no one point); nor is a
    marker that keeps still on the group (1 mm noise: its path fits a sphere of 3 mm about a point beside
    it, within a level of 2 mm), nor one that turns 3 degrees (a short arc: the fit takes a small sphere)."""
    from mocapskel.solvers.rotations import rotvec_to_matrix
    from mocapskel.solvers.grouping.grouping import turns_about_a_point

    rng = np.random.default_rng(0)
    K = 300
    centre, arm = np.array([60.0, 40.0, -30.0]), np.array([0.0, 0.0, -90.0])
    group = np.arange(3)
    for seed, deg in [(0, 35.0), (1, 25.0)]:
        turn = rotvec_to_matrix(rng.uniform(-1, 1, (K, 3)) * np.radians(deg) * np.array([1.0, 1.0, 0.3]))
        P = _group_and_marker(centre + turn @ arm, seed)
        assert turns_about_a_point(P, 3, group, 1.5)
        assert not turns_about_a_point(P[:, [0, 1, 3]], 2, group[:2], 1.5)  # two markers fix no frame
    skin = centre + arm + rng.normal(0, 12.0, (K, 3))  # as far about its place, on no sphere
    assert not turns_about_a_point(_group_and_marker(skin, 2), 3, group, 1.5)
    turn = rotvec_to_matrix(rng.uniform(-1, 1, (K, 3)) * np.radians(35.0) * np.array([1.0, 1.0, 0.3]))
    second = (np.arange(K) >= K // 2)[:, None] * np.array([0.0, 0.0, 40.0])
    two = centre - second + np.einsum("kij,kj->ki", turn, arm + second)
    assert not turns_about_a_point(_group_and_marker(two, 6), 3, group, 1.5)
    for seed in [3, 4]:
        assert not turns_about_a_point(_group_and_marker(np.broadcast_to(centre + arm, (K, 3)), seed), 3, group, 2.0)
    small = rotvec_to_matrix(rng.uniform(-1, 1, (K, 3)) * np.radians(3.0))
    assert not turns_about_a_point(_group_and_marker(centre + small @ arm, 5), 3, group, 2.0)
