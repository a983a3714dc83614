"""Property-based tests (hypothesis) of the readers and of the pipeline (issue 6).

- TRC and C3D: random small takes with gaps, random labels and units survive
  write → read; random garbage (and damaged copies of a good file) either
  reads or raises InputError, never anything else.
- ``pipeline.fit`` on random small trees of rigid segments either succeeds or
  raises a MocapskelError (exit 2/3/4 on the command line), never anything else.

Example counts are small so that the module runs in well under a minute.
"""
from __future__ import annotations

import os
import re
import string
import tempfile
from pathlib import Path

import ezc3d
import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from mocapskel import pipeline
from mocapskel.artifacts import Markers
from mocapskel.cache import Cache
from mocapskel.errors import InputError, MocapskelError
from mocapskel.io.markers import computed_reason, read_markers, write_markers
from mocapskel.synth.chains import hang_tree

UNIT_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0}
#: MOCAPSKEL_HYPOTHESIS_SCALE=20 runs 20 times as many examples (a longer hunt; the suite uses 1).
SCALE = max(1, int(os.environ.get("MOCAPSKEL_HYPOTHESIS_SCALE", "1")))
#: The suite draws the same examples every run (a CI run is reproducible); a longer hunt draws at random.
RANDOM = SCALE > 1
COMMON = settings(max_examples=25 * SCALE, deadline=10_000, derandomize=not RANDOM, suppress_health_check=[HealthCheck.too_slow])

# --------------------------------------------------------------------------- strategies

label = st.text(alphabet=string.ascii_letters + string.digits + "_-.", min_size=1, max_size=12).filter(
    lambda s: s[0].isalpha() and computed_reason(s) is None
)


@st.composite
def takes(draw) -> tuple[np.ndarray, tuple[str, ...], float]:
    """(F, M, 3) points in mm with whole-sample NaN gaps, unique labels, a rate."""
    F = draw(st.integers(1, 12))
    M = draw(st.integers(1, 5))
    coords = st.floats(-5000.0, 5000.0, allow_nan=False, allow_infinity=False, width=32)
    pts = draw(arrays(np.float64, (F, M, 3), elements=coords))
    gaps = draw(arrays(np.bool_, (F, M)))
    pts[gaps] = np.nan
    labels = tuple(draw(st.lists(label, min_size=M, max_size=M, unique_by=str.lower)))
    rate = draw(st.sampled_from([30.0, 60.0, 100.0, 120.0, 148.5, 200.0]))
    return pts, labels, rate


_TMP = tempfile.TemporaryDirectory(prefix="mocapskel-prop-")


@pytest.fixture(scope="module", autouse=True)
def _remove_tmp():
    yield
    _TMP.cleanup()


def _tmpdir() -> Path:
    """A fresh folder for one example (hypothesis examples cannot use pytest's tmp_path)."""
    return Path(tempfile.mkdtemp(dir=_TMP.name))


def _same_gaps(read: np.ndarray, expect: np.ndarray) -> None:
    np.testing.assert_array_equal(np.isnan(read), np.isnan(expect))


# --------------------------------------------------------------------------- round trips


@COMMON
@given(takes(), st.sampled_from(sorted(UNIT_MM)))
def test_trc_round_trip(take, units: str) -> None:
    """A hand-written TRC in m, cm or mm (exact decimal text) reads back as the same points in mm."""
    pts, labels, rate = take
    F, M = pts.shape[:2]
    k = UNIT_MM[units]
    vals = pts / k
    head = (
        "PathFileType\t4\t(X/Y/Z)\tp.trc\n"
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames\n"
        f"{rate!r}\t{rate!r}\t{F}\t{M}\t{units}\t{rate!r}\t1\t{F}\n"
        "Frame#\tTime\t" + "\t\t\t".join(labels) + "\n"
        "\t\t" + "\t".join(f"X{i}\tY{i}\tZ{i}" for i in range(1, M + 1)) + "\n\n"
    )
    rows = [
        f"{i + 1}\t{i / rate!r}\t" + "\t".join("" if np.isnan(v) else repr(float(v)) for v in vals[i].ravel())
        for i in range(F)
    ]
    f = _tmpdir() / "p.trc"
    f.write_text(head + "\n".join(rows) + "\n")
    if np.isnan(pts).all():
        with pytest.raises(InputError, match="no marker data"):
            read_markers(f)
        return
    m = read_markers(f)
    assert m.labels == labels and m.rate == rate and m.units == units
    _same_gaps(m.points, pts)
    np.testing.assert_allclose(m.points, pts, rtol=1e-12, atol=1e-9)


@COMMON
@given(takes())
def test_trc_writer_round_trip(take) -> None:
    """write_markers → read_markers through TRC: 6 decimals, gaps kept."""
    pts, labels, rate = take
    f = _tmpdir() / "w.trc"
    write_markers(f, Markers(points=pts, labels=labels, rate=rate))
    if np.isnan(pts).all():
        with pytest.raises(InputError, match="no marker data"):
            read_markers(f)
        return
    m = read_markers(f)
    assert m.labels == labels and m.rate == rate
    _same_gaps(m.points, pts)
    np.testing.assert_allclose(m.points, pts, rtol=0, atol=5.1e-7)


@COMMON
@given(takes(), st.sampled_from(sorted(UNIT_MM)))
def test_c3d_round_trip(take, units: str) -> None:
    """A float C3D in m, cm or mm reads back as its float32 values times the unit; (0, 0, 0) is a gap."""
    pts, labels, rate = take
    F, M = pts.shape[:2]
    k = UNIT_MM[units]
    stored = np.float32(np.nan_to_num(pts) / k)  # what the file holds
    seen = np.isfinite(pts).all(axis=2)
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [rate]
    c["parameters"]["POINT"]["LABELS"]["value"] = list(labels)
    c["parameters"]["POINT"]["UNITS"]["value"] = [units]
    data = np.ones((4, M, F))
    data[:3] = stored.astype(np.float64).transpose(2, 1, 0)
    c["data"]["points"] = data
    c["data"]["meta_points"]["residuals"] = np.where(seen, 0.0, -1.0).T[None]
    c["data"]["meta_points"]["camera_masks"] = np.zeros((7, M, F), dtype=bool)
    f = _tmpdir() / "p.c3d"
    c.write(str(f))
    expect = stored.astype(np.float64) * k
    expect[~seen | (stored == 0).all(axis=2)] = np.nan
    if np.isnan(expect).all():
        with pytest.raises(InputError, match="no marker data"):
            read_markers(f)
        return
    m = read_markers(f)
    assert m.labels == labels and m.units == units
    assert m.rate == pytest.approx(rate, rel=1e-7)  # stored as float32
    _same_gaps(m.points, expect)
    np.testing.assert_array_equal(m.points, expect)


@COMMON
@given(takes())
def test_c3d_writer_round_trip(take) -> None:
    pts, labels, rate = take
    f = _tmpdir() / "w.c3d"
    write_markers(f, Markers(points=pts, labels=labels, rate=rate))
    expect = np.float32(pts).astype(np.float64)
    expect[(expect == 0).all(axis=2)] = np.nan
    if np.isnan(expect).all():
        with pytest.raises(InputError):
            read_markers(f)
        return
    m = read_markers(f)
    assert m.labels == labels
    _same_gaps(m.points, expect)
    np.testing.assert_array_equal(m.points, expect)


# --------------------------------------------------------------------------- garbage


def _reads_or_input_error(path: Path) -> None:
    try:
        m = read_markers(path)
    except InputError as e:
        assert path.name in str(e) and " — " in str(e), str(e)
        return
    assert m.points.ndim == 3 and m.points.shape[2] == 3 and m.n_frames > 0 and m.n_markers > 0
    assert len(set(m.labels)) == m.n_markers


@COMMON
@given(st.text(max_size=400) | st.binary(max_size=400))
def test_garbage_trc(blob) -> None:
    f = _tmpdir() / "g.trc"
    f.write_bytes(blob.encode("utf-8", "surrogatepass") if isinstance(blob, str) else blob)
    _reads_or_input_error(f)


TRC_HEADER = (
    "PathFileType\t4\t(X/Y/Z)\tg.trc\n"
    "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames\n"
    "100\t100\t3\t2\tmm\t100\t1\t3\n"
    "Frame#\tTime\tA\t\t\tB\n"
    "\t\tX1\tY1\tZ1\tX2\tY2\tZ2\n\n"
)


@COMMON
@given(st.lists(st.lists(st.sampled_from(["", "1", "-2.5", "1e3", "nan", "inf", "x", " ", "1,5", "0x1F", "1.2.3"]),
                         max_size=10), max_size=6))
def test_trc_with_garbage_fields(rows: list[list[str]]) -> None:
    f = _tmpdir() / "g.trc"
    f.write_text(TRC_HEADER + "".join("\t".join(r) + "\n" for r in rows))
    _reads_or_input_error(f)


@pytest.fixture(scope="module")
def good_files(tmp_path_factory) -> dict[str, bytes]:
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(20, 4, 3)) * 300 + 1000
    pts[3, 1] = np.nan
    d = tmp_path_factory.mktemp("good")
    out = {}
    for ext in (".c3d", ".trc"):
        write_markers(d / f"g{ext}", Markers(points=pts, labels=("A", "B", "C", "D"), rate=100.0))
        out[ext] = (d / f"g{ext}").read_bytes()
    return out


@settings(max_examples=40 * SCALE, deadline=10_000, derandomize=not RANDOM, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_damaged_copies_of_a_good_file(good_files: dict[str, bytes], data) -> None:
    """Truncate a good C3D/TRC anywhere, or overwrite a few bytes anywhere (header, parameters, data)."""
    ext = data.draw(st.sampled_from([".c3d", ".trc"]))
    b = bytearray(good_files[ext])
    if data.draw(st.booleans()):
        b = b[: data.draw(st.integers(0, len(b) - 1))]
    else:
        for _ in range(data.draw(st.integers(1, 8))):
            i = data.draw(st.integers(0, min(len(b) - 1, 1600) if ext == ".c3d" else len(b) - 1))
            b[i] = data.draw(st.integers(0, 255))
    f = _tmpdir() / f"d{ext}"
    f.write_bytes(bytes(b))
    _reads_or_input_error(f)


@COMMON
@given(st.binary(min_size=1, max_size=3000))
def test_garbage_c3d(blob: bytes) -> None:
    f = _tmpdir() / "g.c3d"
    f.write_bytes(blob)
    _reads_or_input_error(f)


@COMMON
@given(st.binary(min_size=0, max_size=2000))
def test_garbage_behind_a_c3d_first_word(blob: bytes) -> None:
    f = _tmpdir() / "g.c3d"
    f.write_bytes(bytes([2, 0x50]) + blob)
    _reads_or_input_error(f)


# --------------------------------------------------------------------------- the pipeline on random skeletons


@st.composite
def skeletons(draw) -> Markers:
    S = draw(st.integers(1, 4))
    parent = [-1] + [draw(st.integers(0, i - 1)) for i in range(1, S)]
    counts = [draw(st.integers(1, 4)) for _ in range(S)]
    frames = draw(st.integers(2, 60) | st.integers(60, 400))  # at 100 Hz: too short to fit, and long enough
    seed = draw(st.integers(0, 2**32 - 1))
    noise = draw(st.sampled_from([0.0, 0.5, 2.0]))
    rng = np.random.default_rng(seed)
    take = hang_tree(parent, counts, frames, rng=rng, link_length=300.0, noise=noise)
    pts = take.markers.points.copy()
    gap_fraction = draw(st.sampled_from([0.0, 0.05, 0.3]))
    if gap_fraction:
        for m in range(pts.shape[1]):  # runs of missing frames
            for _ in range(rng.poisson(gap_fraction * frames / 40)):
                s = int(rng.integers(0, frames))
                pts[s : s + int(rng.integers(1, 20)), m] = np.nan
    if draw(st.booleans()) and frames > 20:  # every marker lost at once for a stretch
        s = int(rng.integers(0, frames - 10))
        pts[s : s + 10] = np.nan
    return Markers(points=pts, labels=take.markers.labels, rate=take.markers.rate, source="random.trc")


@settings(max_examples=25 * SCALE, deadline=30_000, derandomize=not RANDOM, suppress_health_check=[HealthCheck.too_slow])
@given(skeletons())
def test_fit_random_skeleton_succeeds_or_raises_a_mocapskel_error(markers: Markers) -> None:
    try:
        res = pipeline.fit(markers, pipeline.make_params(), cache=Cache(None))
    except MocapskelError as e:
        event(f"{type(e).__name__}: {str(e).split(':')[1][:40]}")
        assert e.exit_code in (2, 3, 4), repr(e)
        assert re.search(r"\w", str(e))
        return
    event(f"fitted {markers.n_markers} markers")
    F = markers.n_frames
    assert res.bvh.root_pos.shape == (F, 3)
    assert res.bvh.local_rot.shape[0] == F
    assert np.isfinite(res.bvh.root_pos).all() and np.isfinite(res.bvh.local_rot).all()
