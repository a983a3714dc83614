import numpy as np
import pytest

from mocapskel import artifacts, pipeline
from mocapskel.errors import InputError
from mocapskel.io import artifact_files


def test_every_artifact_round_trips_through_npz(tmp_path, linkage):
    run = pipeline.run_until(linkage.markers, "ik")
    obj = run.artifact
    chain = []
    while obj is not None:
        chain.append(obj)
        obj = {"motion": lambda o: o.skeleton, "skeleton": lambda o: o.joints, "joints": lambda o: o.topology,
               "topology": lambda o: o.segments, "segments": lambda o: o.markers}.get(obj.kind, lambda o: None)(obj)
    assert [o.kind for o in chain] == ["motion", "skeleton", "joints", "topology", "segments", "markers"]
    for o in chain:
        p = tmp_path / f"{o.kind}.npz"
        artifact_files.save(o, p)
        back = artifact_files.load(p)
        assert type(back) is type(o)
        assert pipeline.stage_of(back) == pipeline.stage_of(o)
        np.testing.assert_array_equal(artifacts.markers_of(back).points, artifacts.markers_of(o).points)
        assert artifacts.markers_of(back).labels == artifacts.markers_of(o).labels
    m = artifact_files.load(tmp_path / "motion.npz")
    np.testing.assert_array_equal(m.rot, chain[0].rot)
    assert m.skeleton.names == chain[0].skeleton.names
    assert m.skeleton.joints.method == chain[0].skeleton.joints.method


def test_load_refuses_non_artifacts(tmp_path):
    p = tmp_path / "x.npz"
    np.savez(p, a=np.zeros(3))
    with pytest.raises(InputError, match="not a mocapskel artifact"):
        artifact_files.load(p)
    q = tmp_path / "y.npz"
    q.write_bytes(b"garbage")
    with pytest.raises(InputError, match="y.npz"):
        artifact_files.load(q)
