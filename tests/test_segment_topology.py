import numpy as np
import pytest

from mocapskel import pipeline
from mocapskel.errors import DataError
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
