"""--markers-out: a C3D take keeps everything it holds, with the joint centres added; TRC for OpenSim."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from mocapskel.cli.main import cli

REPO = Path(__file__).resolve().parents[1]
QUALISYS = REPO.parent / "shared" / "realdata" / "ezc3d" / "Qualisys.c3d"

#: Parameters that must change when points are added (the data block moves; the labels grow).
CHANGED = {("POINT", "USED"), ("POINT", "LABELS"), ("POINT", "DESCRIPTIONS"), ("POINT", "DATA_START"), ("ROTATION", "DATA_START")}


def _run(*args: str) -> None:
    res = CliRunner().invoke(cli, list(args), catch_exceptions=False)
    assert res.exit_code == 0, res.output


def _same(a, b) -> bool:
    a, b = np.asarray(a), np.asarray(b)
    if a.dtype.kind in "fc" or b.dtype.kind in "fc":
        return a.shape == b.shape and np.array_equal(a, b, equal_nan=True)
    return a.shape == b.shape and bool(np.all(a == b))


def _check_take_kept(src: Path, out: Path, motion_jc: np.ndarray | None = None) -> list[str]:
    """Everything of ``src`` is in ``out`` unchanged; returns the added labels."""
    import ezc3d

    a = ezc3d.c3d(str(src), extract_forceplat_data=True)
    b = ezc3d.c3d(str(out), extract_forceplat_data=True)
    assert np.array_equal(a["data"]["analogs"], b["data"]["analogs"])  # bit for bit
    P = a["data"]["points"].shape[1]
    assert np.array_equal(a["data"]["points"], b["data"]["points"][:, :P], equal_nan=True)
    assert np.array_equal(a["data"]["meta_points"]["residuals"], b["data"]["meta_points"]["residuals"][:, :P])
    for g in a["parameters"]:
        for k, v in a["parameters"][g].items():
            if k == "__METADATA__" or (g, k) in CHANGED:
                continue
            assert k in b["parameters"][g], f"{g}:{k} lost"
            assert _same(v["value"], b["parameters"][g][k]["value"]), f"{g}:{k} changed"
    la = list(a["parameters"]["POINT"]["LABELS"]["value"])
    lb = list(b["parameters"]["POINT"]["LABELS"]["value"])
    assert lb[:P] == la  # namespaces and labels as written
    assert len(a["data"]["platform"]) == len(b["data"]["platform"])
    for pa, pb in zip(a["data"]["platform"], b["data"]["platform"]):
        for key in ("force", "moment", "center_of_pressure", "Tz", "corners", "origin", "cal_matrix"):
            assert _same(pa[key], pb[key]), key
    assert a["header"]["points"]["first_frame"] == b["header"]["points"]["first_frame"]
    added = lb[P:]
    desc = list(b["parameters"]["POINT"]["DESCRIPTIONS"]["value"])[P:]
    assert len(desc) == len(added) and all("joint centre between" in d and "found by" in d for d in desc)
    assert all(s.endswith("_JC") for s in added)
    return added


def test_markers_out_keeps_qualisys_analogs_force_plates_events_bit_for_bit(tmp_path: Path) -> None:
    if not QUALISYS.exists():
        pytest.skip(f"the shared real data is absent ({QUALISYS.name} not found beside the repository): "
                    "cannot check --markers-out on ezc3d's Qualisys sample")
    import ezc3d

    out = tmp_path / "q_jc.c3d"
    _run("fit", str(QUALISYS), "-o", str(tmp_path / "q.bvh"), "--markers-out", str(out), "--no-cache", "-q")
    added = _check_take_kept(QUALISYS, out)
    a = ezc3d.c3d(str(QUALISYS), extract_forceplat_data=True)
    assert a["data"]["analogs"].shape[1] == 69
    assert len(a["data"]["platform"]) == 2
    assert len(a["parameters"]["EVENT"]["LABELS"]["value"]) == 7
    from mocapskel.io.bvh_read import read_bvh

    skel = read_bvh(tmp_path / "q.bvh")[0]
    assert len(added) == skel.n_joints - 1  # one joint centre per joint of the tree
    # generic names: <parent>_<child>_JC after the BVH's segment names
    names = set(skel.names)
    for lab in added:
        parts = lab[: -len("_JC")]
        assert any(parts == f"{p}_{c}" for p in names for c in names), lab


def _generated_c3d(path: Path, markers, namespace: str = "Subj") -> None:
    """A C3D with what a lab file has: namespaced labels, analogs, two force plates, events, TRIAL/SUBJECTS."""
    import ezc3d

    pts = markers.points
    F, M = pts.shape[:2]
    rng = np.random.default_rng(7)
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [float(markers.rate)]
    c["parameters"]["POINT"]["UNITS"]["value"] = ["mm"]
    c["parameters"]["POINT"]["LABELS"]["value"] = [f"{namespace}:{s}" for s in markers.labels]
    data = np.zeros((4, M, F))
    seen = np.isfinite(pts).all(axis=2)
    data[:3] = np.where(seen[..., None], pts, 0.0).transpose(2, 1, 0)
    data[3] = 1.0
    c["data"]["points"] = data
    res = rng.uniform(0.1, 2.0, (1, M, F))
    res[0][~seen.T] = -1.0
    c["data"]["meta_points"]["residuals"] = res
    n_an, sub = 12, 5
    c["parameters"]["ANALOG"]["RATE"]["value"] = [float(markers.rate) * sub]
    c["parameters"]["ANALOG"]["LABELS"]["value"] = [f"{a}{k}" for k in (1, 2) for a in ("Fx", "Fy", "Fz", "Mx", "My", "Mz")]
    c["parameters"]["ANALOG"]["UNITS"]["value"] = ["N"] * 3 + ["Nmm"] * 3 + ["N"] * 3 + ["Nmm"] * 3
    c["data"]["analogs"] = rng.normal(0, 100, (1, n_an, F * sub)).astype(np.float32).astype(np.float64)
    corners = np.zeros((3, 4, 2))
    for p, x0 in enumerate((0.0, 600.0)):
        corners[:, :, p] = np.array([[x0 + 500, 400, 0], [x0, 400, 0], [x0, 0, 0], [x0 + 500, 0, 0]]).T
    c.add_parameter("FORCE_PLATFORM", "CORNERS", corners)
    c.add_parameter("FORCE_PLATFORM", "ORIGIN", np.array([[1.0, 2.0, -40.0], [-1.0, 2.5, -41.0]]).T)
    # integer parameters (ezc3d 1.7's add_parameter stores none as INT): set as its writer reads them
    for name, value in (("USED", [2]), ("TYPE", [2, 2]), ("ZERO", [1, 0]), ("CHANNEL", np.arange(1, 13).reshape(2, 6).T)):
        c["parameters"]["FORCE_PLATFORM"][name] = {
            "type": ezc3d.ezc3d.INT, "value": np.asarray(value), "description": "", "is_locked": False}
    c.add_parameter("TRIAL", "CAMERA_RATE", [float(markers.rate)])
    c.add_parameter("SUBJECTS", "NAMES", [namespace])
    c.add_parameter("SUBJECTS", "USES_PREFIXES", [1])
    for t, lab, ctx in ((0.5, "Foot Strike", "Left"), (1.1, "Foot Off", "Right"), (1.9, "Foot Strike", "Right")):
        c.add_event(time=[0, t], context=ctx, label=lab)
    c.write(str(path))


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    """A generated human take in a C3D with what a lab file holds, fitted once."""
    from mocapskel import pipeline
    from mocapskel.synth.presets import Recipe, make

    d = tmp_path_factory.mktemp("lab")
    take = make(Recipe(kind="human", frames=300, rate=100.0, noise_mm=1.0, soft_tissue_mm=1.0, seed=5))
    src = d / "lab.c3d"
    _generated_c3d(src, take.markers)
    res = pipeline.fit(src, pipeline.make_params())
    return take, src, res


def test_markers_out_keeps_a_generated_lab_file_and_adds_humanoid_joint_points(lab, tmp_path: Path) -> None:
    import ezc3d

    from mocapskel.cli.fit import write_markers_out
    from mocapskel.pipeline import ReadOptions

    take, src, res = lab
    out = tmp_path / "lab_jc.c3d"
    write_markers_out(out, res.motion, src, ReadOptions(), res.bvh)
    added = _check_take_kept(src, out)
    b = ezc3d.c3d(str(out))
    ev = b["parameters"]["EVENT"]
    assert list(ev["LABELS"]["value"]) == ["Foot Strike", "Foot Off", "Foot Strike"]
    assert np.allclose(ev["TIMES"]["value"][1], [0.5, 1.1, 1.9])
    # the generated human is recognised: joint points named after the joint
    truth = take.truth
    assert "LeftKnee_JC" in added and "RightHip_JC" in added and "Lumbar_JC" in added
    # LeftKnee_JC is the generated left knee (truth joint centres, within a fit's error)
    jn = list(truth.info["joint_names"])
    P = len(take.markers.labels)
    lk = b["data"]["points"][:3, P + added.index("LeftKnee_JC")].T
    true_lk = truth.joints[:, jn.index("LKnee")]
    err = np.linalg.norm(lk - true_lk, axis=1)
    # on this 3-s take the knee, and its neighbours hip and ankle, turn like hinges: the markers fix
    # the knee's axis but not where along it the centre sits (it stays nearest the markers)
    assert np.median(err) < 40.0, np.median(err)
    rk = truth.joints[:, jn.index("RKnee")]
    assert np.median(np.linalg.norm(lk - rk, axis=1)) > 100.0  # and not the right one


def test_markers_out_trc_reads_in_opensim(lab, tmp_path: Path) -> None:
    osim = pytest.importorskip("opensim", reason="the opensim package is not installed: cannot check the TRC in OpenSim")
    from mocapskel.cli.fit import write_markers_out
    from mocapskel.pipeline import ReadOptions

    take, src, res = lab
    out = tmp_path / "t_jc.trc"
    write_markers_out(out, res.motion, src, ReadOptions(), res.bvh)
    table = osim.TimeSeriesTableVec3(str(out))
    labels = list(table.getColumnLabels())
    assert labels[: len(take.markers.labels)] == list(take.markers.labels)  # the namespace removed
    assert "LeftKnee_JC" in labels
    F = take.markers.n_frames
    assert table.getNumRows() == F
    assert table.getTableMetaDataAsString("Units") == "mm"
    assert float(table.getTableMetaDataAsString("DataRate")) == pytest.approx(100.0)
    times = np.array(table.getIndependentColumn())
    assert np.allclose(times, np.arange(F) / 100.0, atol=1e-6)
    col = table.getDependentColumn("LTHI1")
    got = np.array([[col[i][k] for k in range(3)] for i in range(F)])
    want = take.markers.points[:, list(take.markers.labels).index("LTHI1")]
    ok = np.isfinite(want).all(axis=1)
    assert np.allclose(got[ok], want[ok], atol=1e-5)


def test_added_points_continue_labels2_beyond_255_points(tmp_path: Path) -> None:
    from mocapskel.artifacts import Markers
    from mocapskel.io.c3d_write import write_c3d
    from mocapskel.io.c3d_points import add_points
    from mocapskel.io.markers import read_markers

    rng = np.random.default_rng(0)
    F, M = 20, 260
    pts = rng.normal(size=(F, M, 3)) * 100
    write_c3d(tmp_path / "many.c3d", Markers(points=pts, labels=tuple(f"P{i}" for i in range(M)), rate=100.0))
    new = rng.normal(size=(F, 3, 3)) * 100
    new[3, 1] = np.nan
    got = add_points(tmp_path / "many.c3d", tmp_path / "jc.c3d", ["A_JC", "P7", "C_JC"], ["a", "b", "c"], new)
    assert got == ["A_JC", "P7_2", "C_JC"]  # a label already in the file gets a suffix
    back = read_markers(tmp_path / "jc.c3d", include=("*",))
    assert back.labels[-4:] == ("P259", "A_JC", "P7_2", "C_JC") and back.n_markers == M + 3
    np.testing.assert_allclose(back.points[:, -3:], new, atol=1e-3)  # float32 storage; the NaN a gap
    np.testing.assert_array_equal(back.points[:, :M], np.asarray(pts, dtype=np.float32).astype(np.float64))


def test_added_points_are_written_in_the_files_units(tmp_path: Path) -> None:
    import ezc3d

    from mocapskel.io.c3d_points import add_points
    from mocapskel.io.markers import read_markers

    rng = np.random.default_rng(1)
    F, M = 30, 4
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [50.0]
    c["parameters"]["POINT"]["UNITS"]["value"] = ["m"]
    c["parameters"]["POINT"]["LABELS"]["value"] = ["A", "B", "C", "D"]
    data = np.ones((4, M, F))
    data[:3] = rng.normal(size=(3, M, F))
    c["data"]["points"] = data
    c.write(str(tmp_path / "m.c3d"))
    jc_mm = rng.normal(size=(F, 2, 3)) * 1000
    add_points(tmp_path / "m.c3d", tmp_path / "m_jc.c3d", ["X_JC", "Y_JC"], ["x", "y"], jc_mm)
    back = read_markers(tmp_path / "m_jc.c3d", include=("*",))  # mm, from the file's metres
    assert back.units == "m"
    np.testing.assert_allclose(back.points[:, -2:], jc_mm, rtol=1e-6, atol=1e-3)
    b = ezc3d.c3d(str(tmp_path / "m_jc.c3d"))
    np.testing.assert_allclose(b["data"]["points"][:3, M:].T, jc_mm.transpose(0, 1, 2) / 1000, atol=1e-6)
