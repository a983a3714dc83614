"""TRC reading and writing, and what read_markers does for every format (paths, labels, patterns)."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mocapskel.artifacts import Markers
from mocapskel.errors import InputError, UsageError
from mocapskel.io.markers import COMPUTED_POINT_PATTERNS, _clean_labels, computed_reason, read_markers, write_markers
from mocapskel.io.trc import read_trc, write_trc

# --------------------------------------------------------------------------- helpers


def random_markers(rng: np.random.Generator, F: int = 80, M: int = 6, gaps: float = 0.1, rate: float = 100.0) -> Markers:
    pts = rng.normal(size=(F, M, 3)) * 300.0
    pts[rng.random((F, M)) < gaps] = np.nan
    return Markers(points=pts, labels=tuple(f"MK{i}" for i in range(M)), rate=rate)


def trc_text(
    rows: list[str],
    names: list[str],
    *,
    rate: str = "100",
    units: str = "mm",
    nframes: int | None = None,
    sep: str = "\t",
) -> str:
    """A TRC file as OpenSim writes it; ``rows`` are the data lines (already joined with ``sep``)."""
    M = len(names)
    nf = len(rows) if nframes is None else nframes
    head = [
        f"PathFileType{sep}4{sep}(X/Y/Z){sep}x.trc",
        sep.join(["DataRate", "CameraRate", "NumFrames", "NumMarkers", "Units", "OrigDataRate", "OrigDataStartFrame", "OrigNumFrames"]),
        sep.join([rate, rate, str(nf), str(M), units, rate, "1", str(nf)]),
        f"Frame#{sep}Time{sep}" + (sep * 3).join(names) + sep * 2,
        sep * 2 + sep.join(f"X{i}{sep}Y{i}{sep}Z{i}" for i in range(1, M + 1)),
        "",
    ]
    return "\n".join(head + rows) + "\n"


def write_text(path: Path, text: str) -> Path:
    path.write_text(text, newline="")
    return path


def printed(x: np.ndarray) -> np.ndarray:
    """What a %.6f field reads back as."""
    flat = [float(f"{v:.6f}") if np.isfinite(v) else np.nan for v in x.ravel()]
    return np.array(flat).reshape(x.shape)


# --------------------------------------------------------------------------- round trips


def test_round_trip_random_with_gaps(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    m = random_markers(rng, F=120, M=7, gaps=0.2, rate=59.94)
    f = tmp_path / "take.trc"
    write_markers(f, m)
    back = read_markers(f)
    assert back.labels == m.labels
    assert back.rate == 59.94  # the rate is written exactly
    assert back.units == "mm" and back.source == "take.trc" and back.stage == "read"
    np.testing.assert_array_equal(np.isnan(back.points), np.isnan(m.points))
    np.testing.assert_array_equal(back.points, printed(m.points))  # exact to the printed precision
    assert back.info["warnings"] == []
    assert sorted(os.listdir(tmp_path)) == ["take.trc"]


def test_written_trc_is_tab_separated_with_empty_gaps(tmp_path: Path) -> None:
    pts = np.array([[[1.0, 2.0, 3.0], [np.nan, np.nan, np.nan]], [[4.0, 5.0, 6.0], [7.0, 8.0, 9.0]]])
    f = tmp_path / "g.trc"
    write_trc(f, Markers(points=pts, labels=("A", "B"), rate=100.0))
    lines = f.read_text().splitlines()
    assert lines[0].startswith("PathFileType\t4\t(X/Y/Z)")
    assert lines[2].split("\t")[:5] == ["100", "100", "2", "2", "mm"]
    assert lines[3] == "Frame#\tTime\tA\t\t\tB"
    assert lines[6] == "1\t0.000000\t1.000000\t2.000000\t3.000000\t\t\t"
    assert lines[7].startswith("2\t0.010000\t4.000000")


@pytest.mark.parametrize(("units", "factor", "name"), [("mm", 1.0, "mm"), ("cm", 10.0, "cm"), ("m", 1000.0, "m"), (" M ", 1000.0, "m")])
def test_units_are_converted_to_mm(tmp_path: Path, units: str, factor: float, name: str) -> None:
    rows = ["1\t0.00\t0.5\t1.25\t-2", "2\t0.01\t0.25\t1\t2"]
    m = read_markers(write_text(tmp_path / "u.trc", trc_text(rows, ["A"], units=units)))
    assert m.units == name
    np.testing.assert_allclose(m.points[:, 0], np.array([[0.5, 1.25, -2], [0.25, 1, 2]]) * factor, rtol=1e-12)


def test_whitespace_separated_crlf(tmp_path: Path) -> None:
    rows = ["1 0.00 1 2 3 4 5 6", "2   0.01   7 8 9   10 11 12"]
    text = trc_text(rows, ["A", "B"], sep=" ").replace("\n", "\r\n")
    m = read_markers(write_text(tmp_path / "ws.trc", text))
    assert m.labels == ("A", "B")
    np.testing.assert_array_equal(m.points.reshape(2, 6), [[1, 2, 3, 4, 5, 6], [7, 8, 9, 10, 11, 12]])


def test_empty_fields_and_short_rows_are_gaps(tmp_path: Path) -> None:
    rows = [
        "1\t0.00\t1\t2\t3\t\t\t\t7\t8\t9",  # B empty
        "2\t0.01\t1\t2\t3",  # B and C missing: trailing gaps
        "3\t0.02\t\t\t\t4\t5\t6\t7\t8\t9\t",  # A empty, trailing tab
    ]
    m = read_markers(write_text(tmp_path / "e.trc", trc_text(rows, ["A", "B", "C"])))
    seen = ~np.isnan(m.points).any(axis=2)
    np.testing.assert_array_equal(seen, [[1, 0, 1], [1, 0, 0], [0, 1, 1]])
    np.testing.assert_array_equal(m.points[2, 1], [4, 5, 6])


def test_numframes_that_disagrees_uses_the_rows(tmp_path: Path) -> None:
    rows = [f"{i + 1}\t{i / 100:.2f}\t1\t2\t3" for i in range(4)]
    m = read_markers(write_text(tmp_path / "n.trc", trc_text(rows, ["A"], nframes=10)))
    assert m.n_frames == 4
    assert any("NumFrames says 10" in w for w in m.info["warnings"])


def test_rate_from_time_column_when_datarate_is_missing(tmp_path: Path) -> None:
    rows = [f"{i + 1}\t{i / 250:.6f}\t1\t2\t3" for i in range(5)]
    text = trc_text(rows, ["A"], rate="NaN")
    m = read_markers(write_text(tmp_path / "t.trc", text))
    assert m.rate == pytest.approx(250.0)
    assert any("Time column" in w for w in m.info["warnings"])


def test_infinite_values_are_gaps_and_counted(tmp_path: Path) -> None:
    rows = ["1\t0.00\t1\tinf\t3\t4\t5\t6", "2\t0.01\t-inf\t2\t3\tnan\t5\t6"]
    m = read_markers(write_text(tmp_path / "inf.trc", trc_text(rows, ["A", "B"])))
    assert m.info["nonfinite"] == 2
    assert np.isnan(m.points[0, 0]).all() and np.isnan(m.points[1, 0]).all() and np.isnan(m.points[1, 1]).all()
    np.testing.assert_array_equal(m.points[0, 1], [4, 5, 6])


def test_unnamed_columns_with_data_become_markers(tmp_path: Path) -> None:
    rows = ["1\t0.00\t1\t2\t3\t4\t5\t6"]
    m = read_markers(write_text(tmp_path / "x.trc", trc_text(rows, ["A"])))
    assert m.labels == ("A", "M002")
    assert any("no name" in w for w in m.info["warnings"])


def test_large_trc_block_is_read_in_one_parse(tmp_path: Path) -> None:
    """Many rows, irregular lengths: the vectorised path and the field-by-field path agree."""
    rng = np.random.default_rng(3)
    m = random_markers(rng, F=3000, M=12, gaps=0.3)
    f = tmp_path / "big.trc"
    write_trc(f, m)
    text = f.read_text().splitlines()
    text[20] = "\t".join(text[20].split("\t")[:8])  # a short row
    f.write_text("\n".join(text) + "\n")
    back = read_trc(f)
    expected = printed(m.points)
    expected[20 - 6, 2:] = np.nan
    np.testing.assert_array_equal(back.points, expected)


# --------------------------------------------------------------------------- bad TRC input


def _expect_input_error(path: Path, match: str) -> InputError:
    with pytest.raises(InputError, match=match) as ei:
        read_markers(path)
    assert path.name in str(ei.value)
    assert ei.value.exit_code == 3
    assert "—" in str(ei.value)
    return ei.value


def test_header_without_frames(tmp_path: Path) -> None:
    _expect_input_error(write_text(tmp_path / "hdr.trc", trc_text([], ["A", "B"])), "no marker data")


def test_non_numeric_value_names_the_line(tmp_path: Path) -> None:
    rows = ["1\t0.00\t1\t2\t3", "2\t0.01\t1\tabc\t3", "3\t0.02\t1\t2\t3"]
    e = _expect_input_error(write_text(tmp_path / "bad.trc", trc_text(rows, ["A"])), "not a number")
    assert "line 8" in str(e) and "'abc'" in str(e)


def test_text_file_that_is_not_a_trc(tmp_path: Path) -> None:
    _expect_input_error(write_text(tmp_path / "notes.trc", "some notes\nabout the take\n"), "not a TRC file")


def test_csv_file_named_trc(tmp_path: Path) -> None:
    _expect_input_error(write_text(tmp_path / "table.trc", "a,b,c\n1,2,3\n"), "not a TRC file")


def test_random_bytes_named_trc(tmp_path: Path) -> None:
    rng = np.random.default_rng(7)
    f = tmp_path / "noise.trc"
    f.write_bytes(rng.integers(0, 256, 2000, dtype=np.uint8).tobytes())
    _expect_input_error(f, "not a TRC file")


def test_all_nan_trc(tmp_path: Path) -> None:
    rows = ["1\t0.00\t\t\t", "2\t0.01"]
    _expect_input_error(write_text(tmp_path / "nan.trc", trc_text(rows, ["A"])), "no marker data")


def test_trc_without_markers(tmp_path: Path) -> None:
    rows = ["1\t0.00", "2\t0.01"]
    _expect_input_error(write_text(tmp_path / "none.trc", trc_text(rows, [])), "0 markers")


# --------------------------------------------------------------------------- read_markers: paths


@pytest.mark.parametrize("ext", [".c3d", ".trc"])
def test_empty_file(tmp_path: Path, ext: str) -> None:
    f = tmp_path / f"empty{ext}"
    f.write_bytes(b"")
    _expect_input_error(f, "empty file")


def test_unknown_extension(tmp_path: Path) -> None:
    f = tmp_path / "take.bvh"
    f.write_text("HIERARCHY\n")
    _expect_input_error(f, "unknown marker file type")


def test_missing_file(tmp_path: Path) -> None:
    _expect_input_error(tmp_path / "nowhere.c3d", "no such file")


def test_directory(tmp_path: Path) -> None:
    d = tmp_path / "folder.trc"
    d.mkdir()
    _expect_input_error(d, "folder")


def test_extension_is_case_insensitive(tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    m = random_markers(rng, F=5, M=2, gaps=0.0)
    for name in ("UP.TRC", "Up.C3d"):
        write_markers(tmp_path / name, m)
        assert read_markers(tmp_path / name).n_frames == 5


def test_write_unknown_extension_or_missing_folder(tmp_path: Path) -> None:
    m = random_markers(np.random.default_rng(0), F=3, M=2)
    with pytest.raises(UsageError, match="unknown marker file type"):
        write_markers(tmp_path / "x.csv", m)
    with pytest.raises(UsageError, match="folder does not exist"):
        write_markers(tmp_path / "no" / "x.trc", m)


# --------------------------------------------------------------------------- labels


def test_labels_are_cleaned_and_unique(tmp_path: Path) -> None:
    names = ["Sub:LASI", " Sub:RASI ", "Sub:LASI", "", "Sub:LASI"]
    rows = ["1\t0\t" + "\t".join(["1"] * 15)]
    m = read_markers(write_text(tmp_path / "l.trc", trc_text(rows, names)))
    assert m.labels == ("LASI", "RASI", "LASI_2", "M004", "LASI_3")
    assert m.info["namespace"] == ["Sub"]
    assert m.info["renamed"] == {"LASI_2": "LASI", "M004": "", "LASI_3": "LASI"}


def test_prefixes_are_kept_when_two_subjects_share_marker_names() -> None:
    lab = _clean_labels(["ArmL:Marker1", "ArmR:Marker1", "ArmL:Marker2"])
    assert lab.final == ["ArmL:Marker1", "ArmR:Marker1", "ArmL:Marker2"]
    assert lab.namespaces == [] and lab.warnings
    lab2 = _clean_labels(["Box:corner", "Daphne:ASIS", "*0"])
    assert lab2.final == ["corner", "ASIS", "*0"] and lab2.namespaces == ["Box", "Daphne"]


def test_generated_names_avoid_existing_labels() -> None:
    assert _clean_labels(["M002", ""]).final == ["M002", "M002_2"]
    assert _clean_labels(["A", "A_2", "A"]).final == ["A", "A_2", "A_3"]


@settings(max_examples=200, deadline=None)
@given(st.lists(st.sampled_from(["", " ", "A", "A_2", "B", "S:A", "T:A", "S:B", "M001", "M002", "x:", ":y"]), max_size=12))
def test_cleaned_labels_are_always_unique_and_non_empty(raw: list[str]) -> None:
    lab = _clean_labels(raw)
    assert len(lab.final) == len(raw)
    assert len(set(lab.final)) == len(raw)
    assert all(s and s == s.strip() for s in lab.final)


# --------------------------------------------------------------------------- computed points, patterns

COMPUTED = [
    "LHipAngles", "RKneeMoment", "LAnklePower", "LGroundReactionForce", "RNeckAngles", "LAbsAnkleAngle",
    "PELO", "PELA", "PELL", "PELP", "LFEO", "RTIA", "LFOP", "RTOL", "HEDO", "TRXA", "LCLO", "RHUP", "LRAL", "RHNO",
    "LHJC", "RKJC", "L_AJC", "LHipJC", "CentreOfMass", "CentreOfMassFloor", "CenterOfMass",
    "V_Mid_ASIS", "VMID", "VPEL", "VRKN", "VLHI", "VRTO",
]
REAL = [
    "VSAC", "V.Sacral", "LTOE", "LTIB", "RKNE", "LASI", "RPSI", "LFHD", "C7", "T10", "STRN", "CLAV", "LHEE", "RTHI",
    "LELB", "LWRA", "LFIN", "LMT5", "RFT1", "PV1", "pv4", "*12", "*0", "U3", "M001", "Marker_1", "L.Hip", "R.Knee.Lat",
    "AcromionR", "Probe1", "LTHI2", "RLatFoot", "Forehead", "SACR", "LPSI", "RBAK", "L_IAS", "R_FM5", "LFRM", "RUPA",
]


@pytest.mark.parametrize("label", COMPUTED)
def test_computed_labels_are_detected(label: str) -> None:
    assert computed_reason(label) is not None


@pytest.mark.parametrize("label", REAL)
def test_real_marker_labels_are_not_computed(label: str) -> None:
    assert computed_reason(label) is None


def test_pattern_constant_is_documented_pairs() -> None:
    assert all(isinstance(p, str) and isinstance(why, str) and why for p, why in COMPUTED_POINT_PATTERNS)


@pytest.fixture()
def mixed_trc(tmp_path: Path) -> Path:
    names = ["LASI", "RASI", "LKNE", "RKNE", "LHJC", "PELO", "LHipAngles", "*3"]
    rows = [f"{i + 1}\t{i / 100:.2f}\t" + "\t".join(str(v) for v in range(1 + i, 1 + i + 3 * len(names))) for i in range(4)]
    return write_text(tmp_path / "mixed.trc", trc_text(rows, names))


def test_computed_points_are_dropped_and_recorded(mixed_trc: Path) -> None:
    m = read_markers(mixed_trc)
    assert m.labels == ("LASI", "RASI", "LKNE", "RKNE", "*3")
    assert m.info["excluded"] == ["LHJC", "PELO", "LHipAngles"]
    assert m.info["excluded_why"]["LHJC"] == "computed point: joint centre"
    assert m.info["markers_in_file"] == 8 and m.info["markers"] == 5
    # the kept columns are the right ones
    np.testing.assert_array_equal(m.points[0, 4], [22, 23, 24])


def test_exclude_and_include_patterns(mixed_trc: Path) -> None:
    assert read_markers(mixed_trc, exclude=["*KNE"]).labels == ("LASI", "RASI", "*3")
    # any include match overrides the computed-point rule
    assert read_markers(mixed_trc, include=["L*"]).labels == ("LASI", "LKNE", "LHJC", "LHipAngles")
    assert read_markers(mixed_trc, include=["[LR]ASI"]).labels == ("LASI", "RASI")
    # include naming a computed point keeps it; exclude wins over include
    m = read_markers(mixed_trc, include=["LHJC", "LASI", "RASI"], exclude=["RASI"])
    assert m.labels == ("LASI", "LHJC")
    assert m.info["excluded_why"]["RASI"] == "matched by an exclude pattern"
    assert m.info["excluded_why"]["LKNE"] == "not matched by an include pattern"
    # case-sensitive; a pattern that matches nothing is reported
    m = read_markers(mixed_trc, exclude=["lasi"])
    assert "LASI" in m.labels
    assert any("'lasi' matches no label" in w for w in m.info["warnings"])


def test_a_single_pattern_string_is_one_pattern(mixed_trc: Path) -> None:
    assert read_markers(mixed_trc, exclude="*KNE").labels == ("LASI", "RASI", "*3")


def test_patterns_that_leave_nothing(mixed_trc: Path) -> None:
    _expect_input_error_patterns = pytest.raises(InputError, match="include/exclude patterns leave none")
    with _expect_input_error_patterns as ei:
        read_markers(mixed_trc, include=["nothing*"])
    assert "mixed.trc" in str(ei.value)


def test_patterns_also_match_the_label_with_its_prefix(tmp_path: Path) -> None:
    names = ["box:c1", "box:c2", "Ann:LASI"]
    rows = ["1\t0\t" + "\t".join(["1"] * 9)]
    m = read_markers(write_text(tmp_path / "p.trc", trc_text(rows, names)), exclude=["box:*"])
    assert m.labels == ("LASI",)
