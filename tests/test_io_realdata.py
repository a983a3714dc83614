"""Every real take in ``../shared/realdata/`` reads cleanly, or fails with an InputError.

The folder sits beside the repository (it is not committed: see its README).
When it is absent these tests are skipped, and say so.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mocapskel.errors import InputError
from mocapskel.io.c3d import read_c3d
from mocapskel.io.markers import read_markers

REALDATA = Path(__file__).resolve().parents[2] / "shared" / "realdata"
MISSING = f"REAL DATA NOT FOUND at {REALDATA} — the real-file tests did NOT run (see shared/realdata/README.md)"


def _files() -> list[Path]:
    if not REALDATA.is_dir():
        return []
    return sorted(p for p in REALDATA.rglob("*") if p.is_file() and p.suffix.lower() in (".c3d", ".trc"))


FILES = _files()


def _need(rel: str) -> Path:
    if not REALDATA.is_dir():
        pytest.skip(MISSING)
    p = REALDATA / rel
    if not p.is_file():
        pytest.skip(f"{rel} is not in {REALDATA}")
    return p


@pytest.fixture(scope="module")
def takes() -> dict[str, object]:
    """read_markers of every real file (Markers, or the InputError it raised)."""
    out: dict[str, object] = {}
    for p in FILES:
        try:
            out[str(p.relative_to(REALDATA))] = read_markers(p)
        except InputError as e:
            out[str(p.relative_to(REALDATA))] = e
    return out


def test_realdata_folder_is_there() -> None:
    if not FILES:
        pytest.skip(MISSING)
    assert len(FILES) > 10


@pytest.mark.parametrize("rel", [str(p.relative_to(REALDATA)) for p in FILES] or ["<no real data>"])
def test_real_file_reads_sanely_or_raises_input_error(rel: str, takes: dict[str, object]) -> None:
    if not FILES:
        pytest.skip(MISSING)
    m = takes[rel]
    if isinstance(m, InputError):
        assert Path(rel).name in str(m)
        return
    F, M = m.points.shape[:2]
    assert m.points.shape == (F, M, 3) and m.points.dtype == np.float64
    assert F > 0 and M > 0 and m.rate > 0
    assert len(m.labels) == M == len(set(m.labels))
    assert all(s and s == s.strip() for s in m.labels)
    v = m.points[~np.isnan(m.points)]
    assert v.size and np.isfinite(v).all()
    gaps = np.isnan(m.points)
    np.testing.assert_array_equal(gaps, gaps[..., :1].repeat(3, axis=2))  # a gap is a whole point
    assert np.abs(v).max() < 1e5  # mm: a lab is smaller than 100 m
    assert m.info["frames"] == F and m.info["markers"] == M and m.source == Path(rel).name


@pytest.mark.parametrize("rel", [str(p.relative_to(REALDATA)) for p in FILES if p.suffix.lower() == ".c3d"] or ["<no real data>"])
def test_ezc3d_and_numpy_engines_agree(rel: str) -> None:
    if not FILES:
        pytest.skip(MISSING)
    try:
        a = read_c3d(REALDATA / rel, engine="ezc3d")
    except InputError:
        return
    b = read_c3d(REALDATA / rel, engine="numpy")
    np.testing.assert_array_equal(a.points, b.points)
    assert a.labels == b.labels and a.rate == b.rate and a.units == b.units


def test_motion_analysis_virtual_points_and_duplicate_labels() -> None:
    m = read_markers(_need("c3d_org_samples/manufacture_test_motion_analysis_corporation.c3d"))
    excluded = m.info["excluded"]
    assert len(excluded) == 20 and all(s.startswith("V") for s in excluded)
    assert "VSAC" in m.labels  # the real sacral marker stays
    assert not any(s.startswith(("VMID", "VPEL", "VR", "VL")) for s in m.labels)
    # the repeated RKNE RANK LKNE LANK (medial markers, never seen in this walk) are renamed, not lost
    assert {"RKNE_2", "RANK_2", "LKNE_2", "LANK_2"} <= set(m.labels)
    assert m.info["renamed"]["RKNE_2"] == "RKNE"
    assert set(m.info["never_seen"]) == {"RKNE_2", "RANK_2", "LKNE_2", "LANK_2"}
    assert m.n_markers == 29


@pytest.mark.parametrize(
    "rel",
    ["kineticstoolkit/sample_static.c3d", "kineticstoolkit/sprintbasket.c3d", "kineticstoolkit/racing_full.c3d"],
)
def test_kineticstoolkit_metres_come_out_in_mm(rel: str) -> None:
    p = _need(rel)
    m = read_markers(p)
    raw = read_c3d(p, engine="numpy")
    assert m.units == "m"
    spread = np.nanmax(m.points, axis=(0, 1)) - np.nanmin(m.points, axis=(0, 1))
    assert spread.max() > 300  # a person or a wheelchair measured in mm, not in m
    assert np.nanmax(np.abs(raw.points)) > 100


def test_header_that_lies_about_the_frame_count() -> None:
    m = read_markers(_need("ezc3d/Optotrak.c3d"))
    assert m.n_frames == 29
    assert any("1149" in w for w in m.info["warnings"])


def test_subject_prefixes_are_stripped_and_unlabelled_markers_kept() -> None:
    m = read_markers(_need("hdm05/HDM_bd_05-01_01_120.c3d"))
    assert m.info["namespace"] == ["Bastian"]
    assert {"*0", "*1", "*2", "LFHD", "RMT5"} <= set(m.labels)
    assert m.info["excluded"] == []
