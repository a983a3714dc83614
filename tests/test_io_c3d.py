"""C3D reading and writing (mocapskel.io.c3d, through read_markers/write_markers)."""
from __future__ import annotations

import os
import struct
import subprocess
import sys
import textwrap
from pathlib import Path

import ezc3d
import numpy as np
import pytest

from mocapskel.artifacts import Markers
from mocapskel.errors import InputError
from mocapskel.io.c3d import read_c3d
from mocapskel.io.c3d_layout import read_layout
from mocapskel.io.c3d_write import write_c3d
from mocapskel.io.markers import read_markers, write_markers

# --------------------------------------------------------------------------- helpers


def random_markers(rng: np.random.Generator, F: int = 120, M: int = 7, gaps: float = 0.1, rate: float = 100.0) -> Markers:
    """Random trajectories in mm with gaps at random places."""
    pts = rng.normal(size=(F, M, 3)) * 400.0 + np.array([0.0, 0.0, 1000.0])
    pts[rng.random((F, M)) < gaps] = np.nan
    return Markers(points=pts, labels=tuple(f"MK{i:02d}" for i in range(M)), rate=rate)


def ezc3d_file(
    path: Path,
    xyz: np.ndarray,
    labels: list[str],
    *,
    rate: float = 100.0,
    units: str | None = "mm",
    residual: np.ndarray | None = None,
    descriptions: list[str] | None = None,
    extra: dict[tuple[str, str], object] | None = None,
) -> Path:
    """Build a C3D with ezc3d itself. ``xyz`` is (F, M, 3) in file units, NaN allowed."""
    F, M = xyz.shape[:2]
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [rate]
    c["parameters"]["POINT"]["LABELS"]["value"] = list(labels)
    if units is not None:
        c["parameters"]["POINT"]["UNITS"]["value"] = [units]
    if descriptions is not None:
        c["parameters"]["POINT"]["DESCRIPTIONS"]["value"] = list(descriptions)
    data = np.ones((4, M, F))
    data[:3] = xyz.transpose(2, 1, 0)
    c["data"]["points"] = data
    if residual is not None:
        c["data"]["meta_points"]["residuals"] = residual.T[None].astype(float)
        c["data"]["meta_points"]["camera_masks"] = np.zeros((7, M, F), dtype=bool)
    for (group, name), value in (extra or {}).items():
        c.add_parameter(group, name, value)
    c.write(str(path))
    return path


def raw_c3d(
    path: Path,
    values: np.ndarray,
    labels: list[str],
    *,
    rate: float,
    scale: float,
    processor: str = "intel",
    units: str = "mm",
) -> Path:
    """Write a C3D byte by byte (no ezc3d): integer (scale > 0) or float (scale < 0) storage.

    ``values`` is (F, P, 4): x, y, z and the residual word, as stored.
    """
    F, P = values.shape[:2]
    e = ">" if processor == "mips" else "<"

    def i16(v: int) -> bytes:
        return struct.pack(e + "h", v)

    def f32(v: float) -> bytes:
        if processor == "dec":  # IEEE x 4, 16-bit words swapped
            u = struct.unpack("<I", struct.pack("<f", v * 4.0))[0] if v else 0
            return struct.pack("<HH", u >> 16, u & 0xFFFF)
        return struct.pack(e + "f", v)

    def param(gid: int, name: str, ptype: int, dims: tuple[int, ...], data: bytes, last: bool = False) -> bytes:
        body = struct.pack("b", ptype) + bytes([len(dims)]) + bytes(dims) + data + bytes([0])
        off = 0 if last else len(body) + 2
        return struct.pack("b", len(name)) + struct.pack("b", gid) + name.encode() + i16(off) + body

    def group(gid: int, name: str) -> bytes:
        body = bytes([0])
        return struct.pack("b", len(name)) + struct.pack("b", -gid) + name.encode() + i16(len(body) + 2) + body

    width = max(len(s) for s in labels)
    lab = b"".join(s.encode().ljust(width) for s in labels)
    recs = [
        group(1, "POINT"),
        param(1, "USED", 2, (), i16(P)),
        param(1, "FRAMES", 2, (), i16(F)),
        param(1, "SCALE", 4, (), f32(scale)),
        param(1, "RATE", 4, (), f32(rate)),
        param(1, "DATA_START", 2, (), i16(0)),  # patched below
        param(1, "LABELS", -1, (width, P), lab),
        param(1, "UNITS", -1, (len(units),), units.encode()),
        group(2, "ANALOG"),
        param(2, "USED", 2, (), i16(0)),
        param(2, "RATE", 4, (), f32(0.0), last=True),
    ]
    body = b"".join(recs)
    nblocks = (4 + len(body)) // 512 + 1
    data_start = 2 + nblocks
    i = body.index(b"DATA_START") + len(b"DATA_START") + 2 + 2  # offset field, type, ndims
    body = body[:i] + i16(data_start) + body[i + 2:]
    psec = bytes([1, 0x50, nblocks, {"intel": 84, "dec": 85, "mips": 86}[processor]]) + body
    psec = psec.ljust(nblocks * 512, b"\x00")
    head = bytes([2, 0x50]) + i16(P) + i16(0) + i16(1) + i16(F) + i16(0) + f32(scale) + i16(data_start) + i16(0) + f32(rate)
    head = head.ljust(512, b"\x00")
    if scale > 0:
        frames = values.astype(e + "i2").tobytes()
    else:
        frames = b"".join(f32(float(v)) for v in values.ravel()) if processor == "dec" else values.astype(e + "f4").tobytes()
    path.write_bytes(head + psec + frames)
    return path


# --------------------------------------------------------------------------- round trips


def test_round_trip_random_with_gaps(tmp_path: Path) -> None:
    rng = np.random.default_rng(11)
    m = random_markers(rng, F=150, M=9, gaps=0.15, rate=120.0)
    out = tmp_path / "take.c3d"
    write_markers(out, m)
    back = read_markers(out)
    assert back.labels == m.labels
    assert back.rate == 120.0
    assert back.units == "mm" and back.source == "take.c3d" and back.stage == "read"
    assert back.points.dtype == np.float64 and back.points.shape == m.points.shape
    np.testing.assert_array_equal(np.isnan(back.points), np.isnan(m.points))
    # float C3D: exact to float32
    np.testing.assert_array_equal(back.points, m.points.astype(np.float32).astype(np.float64))
    assert back.info["frames"] == 150 and back.info["markers"] == 9
    assert back.info["gaps_fraction"] == pytest.approx(np.isnan(m.points[..., 0]).mean())
    assert back.info["excluded"] == [] and back.info["warnings"] == []


def test_engines_agree_on_written_file(tmp_path: Path) -> None:
    rng = np.random.default_rng(12)
    m = random_markers(rng, F=64, M=5, gaps=0.2)
    out = tmp_path / "t.c3d"
    write_c3d(out, m)
    a, b = read_c3d(out, engine="ezc3d"), read_c3d(out)
    np.testing.assert_array_equal(a.points, b.points)
    assert a.labels == b.labels and a.rate == b.rate
    assert a.info["engine"] == "ezc3d" and b.info["engine"] == "numpy"  # numpy is the default


def test_write_leaves_no_temporary_file_and_keeps_old_file_on_failure(tmp_path: Path) -> None:
    rng = np.random.default_rng(13)
    out = tmp_path / "out.c3d"
    write_markers(out, random_markers(rng, F=10, M=3))
    assert sorted(os.listdir(tmp_path)) == ["out.c3d"]
    before = out.read_bytes()
    bad = Markers(points=np.zeros((5, 3, 3)), labels=("a", "b"), rate=100.0)  # 2 labels for 3 markers
    with pytest.raises(ValueError):
        write_c3d(out, bad)
    assert out.read_bytes() == before
    assert sorted(os.listdir(tmp_path)) == ["out.c3d"]


@pytest.mark.parametrize(
    ("units", "factor", "name"),
    [("mm", 1.0, "mm"), ("cm", 10.0, "cm"), ("m", 1000.0, "m"), ("MM", 1.0, "mm"), (" mm", 1.0, "mm"), ("meters", 1000.0, "m")],
)
def test_units_are_converted_to_mm(tmp_path: Path, units: str, factor: float, name: str) -> None:
    xyz = np.array([[[0.5, 1.25, 2.0], [1.0, 0.25, -0.75]]] * 4)  # (4, 2, 3), exact in float32
    f = ezc3d_file(tmp_path / "u.c3d", xyz, ["A", "B"], units=units)
    m = read_markers(f)
    assert m.units == name
    np.testing.assert_allclose(m.points, xyz * factor, rtol=1e-12)


def test_missing_units_assumed_mm_with_warning(tmp_path: Path) -> None:
    xyz = np.ones((3, 2, 3))
    f = ezc3d_file(tmp_path / "nou.c3d", xyz, ["A", "B"], units="")
    m = read_markers(f)
    assert m.units == "mm"
    assert any("UNITS" in w for w in m.info["warnings"])


def test_labels_beyond_255_come_from_labels2(tmp_path: Path) -> None:
    M = 300
    labels = [f"P{i:03d}" for i in range(M)]
    xyz = np.arange(2 * M * 3, dtype=float).reshape(2, M, 3) + 1.0
    f = ezc3d_file(tmp_path / "many.c3d", xyz, labels)
    lay = read_layout(f)
    assert lay.param("POINT", "LABELS2") is not None  # ezc3d splits the labels itself
    assert len(lay.param("POINT", "LABELS").strings()) == 255
    m = read_markers(f)
    assert m.labels == tuple(labels)
    np.testing.assert_array_equal(m.points, xyz)


def test_zero_coordinates_and_negative_residuals_are_gaps(tmp_path: Path) -> None:
    F, M = 6, 3
    xyz = np.arange(F * M * 3, dtype=float).reshape(F, M, 3) + 10.0
    xyz[2, 1] = 0.0  # exact origin: not seen
    residual = np.zeros((F, M))
    residual[4, 0] = -1.0  # not seen, although the coordinates are there
    f = ezc3d_file(tmp_path / "z.c3d", xyz, ["A", "B", "C"], residual=residual)
    for engine in ("ezc3d", "numpy"):
        raw = read_c3d(f, engine=engine)
        gap = np.isnan(raw.points).all(axis=2)
        assert gap[2, 1] and gap[4, 0]
        assert gap.sum() == 2
    m = read_markers(f)
    assert np.isnan(m.points[2, 1]).all() and np.isnan(m.points[4, 0]).all()
    assert m.info["gaps_fraction"] == pytest.approx(2 / (F * M))


def test_point_that_is_zero_in_one_coordinate_only_is_kept(tmp_path: Path) -> None:
    xyz = np.full((3, 1, 3), 5.0)
    xyz[1, 0, 2] = 0.0
    m = read_markers(ezc3d_file(tmp_path / "z1.c3d", xyz, ["A"]))
    assert m.points[1, 0, 2] == 0.0


def test_namespace_prefix_duplicates_and_empty_labels(tmp_path: Path) -> None:
    xyz = np.ones((2, 5, 3))
    f = ezc3d_file(tmp_path / "ns.c3d", xyz, ["Bob:LASI", "Bob:RASI", "Bob:LASI", "", " Bob:C7 "])
    m = read_markers(f)
    assert m.labels == ("LASI", "RASI", "LASI_2", "M004", "C7")
    assert m.info["namespace"] == ["Bob"]
    assert m.info["renamed"] == {"LASI_2": "LASI", "M004": ""}


def test_computed_points_from_point_group_lists_and_descriptions(tmp_path: Path) -> None:
    xyz = np.ones((3, 5, 3))
    labels = ["LASI", "Foo", "VMID", "RASI", "Bar"]
    desc = ["L.ASIS", "", "V_Mid_ASIS", "R.ASIS", "V_Something"]
    f = ezc3d_file(tmp_path / "pig.c3d", xyz, labels, descriptions=desc, extra={("POINT", "ANGLES"): ["Foo"]})
    m = read_markers(f)
    assert m.labels == ("LASI", "RASI")
    assert m.info["excluded"] == ["Foo", "VMID", "Bar"]
    assert m.info["excluded_why"]["Foo"] == "computed point: listed in POINT:ANGLES"
    assert "description" in m.info["excluded_why"]["Bar"]
    # an include pattern that names a computed point keeps it
    m2 = read_markers(f, include=["*ASI", "Foo"])
    assert m2.labels == ("LASI", "Foo", "RASI")


def test_rate_from_point_rate_when_header_disagrees(tmp_path: Path) -> None:
    f = ezc3d_file(tmp_path / "r.c3d", np.ones((4, 2, 3)), ["A", "B"], rate=200.0)
    b = bytearray(f.read_bytes())
    b[20:24] = struct.pack("<f", 100.0)  # header frame rate
    f.write_bytes(bytes(b))
    m = read_markers(f)
    assert m.rate == 200.0
    assert any("header rate 100" in w for w in m.info["warnings"])


def test_header_frame_count_that_disagrees_with_the_data_is_ignored(tmp_path: Path) -> None:
    f = ezc3d_file(tmp_path / "h.c3d", np.ones((10, 2, 3)), ["A", "B"])
    b = bytearray(f.read_bytes())
    b[8:10] = struct.pack("<H", 7)  # header last frame
    f.write_bytes(bytes(b))
    m = read_markers(f)
    assert m.n_frames == 10
    assert any("header frame range 7" in w for w in m.info["warnings"])


def test_file_ending_cleanly_before_the_declared_frames_uses_the_data(tmp_path: Path) -> None:
    """Like ezc3d's Optotrak sample: 1149 frames declared, 29 stored, the file ends on a frame."""
    xyz = np.arange(20 * 2 * 3, dtype=float).reshape(20, 2, 3) + 1.0
    f = ezc3d_file(tmp_path / "short.c3d", xyz, ["A", "B"])
    lay = read_layout(f)
    f.write_bytes(f.read_bytes()[: (lay.data_start - 1) * 512 + 12 * lay.bytes_per_frame])
    m = read_markers(f)
    assert m.n_frames == 12
    np.testing.assert_array_equal(m.points, xyz[:12])
    assert any("POINT:FRAMES 20" in w for w in m.info["warnings"])


# --------------------------------------------------------------------------- more than 65535 frames


def _long_take(F: int) -> np.ndarray:
    t = np.arange(F, dtype=float)
    xyz = np.stack([np.stack([t % 1000 + 1, t % 777 + 2, np.full(F, 3.0)], 1), np.stack([np.full(F, 5.0), t % 333 + 1, t % 1234 + 7], 1)], 1)
    return xyz  # (F, 2, 3), integers: exact in float32


def test_more_than_65535_frames_from_ezc3d(tmp_path: Path) -> None:
    """ezc3d writes POINT:FRAMES saturated at 65535 and reads back 65535 frames: the rest come from the data block."""
    F = 70_001
    xyz = _long_take(F)
    f = ezc3d_file(tmp_path / "long.c3d", xyz, ["A", "B"], rate=200.0)
    assert read_layout(f).declared_frames() == (65535, "POINT:FRAMES", True)
    for engine in ("ezc3d", "numpy"):
        raw = read_c3d(f, engine=engine)
        assert raw.points.shape == (F, 2, 3)
        np.testing.assert_array_equal(raw.points, xyz)
        assert any("70001 frames" in w for w in raw.warnings)


def test_more_than_65535_frames_round_trip_with_long_frames(tmp_path: Path) -> None:
    F = 66_000
    xyz = _long_take(F)
    xyz[65_999, 1] = np.nan  # a gap in the very last frame must not shorten the take
    f = tmp_path / "long2.c3d"
    write_markers(f, Markers(points=xyz, labels=("A", "B"), rate=100.0))
    assert read_layout(f).declared_frames()[:2] == (F, "POINT:LONG_FRAMES")
    m = read_markers(f)
    assert m.n_frames == F
    np.testing.assert_array_equal(m.points, xyz)


# --------------------------------------------------------------------------- integer storage, processors


@pytest.mark.parametrize("processor", ["intel", "dec", "mips"])
@pytest.mark.parametrize("storage", ["integer", "float"])
def test_scale_and_processor_types_match_ezc3d(tmp_path: Path, processor: str, storage: str) -> None:
    rng = np.random.default_rng(21)
    F, P = 9, 4
    vals = np.zeros((F, P, 4))
    vals[..., :3] = rng.integers(-20000, 20000, size=(F, P, 3))
    vals[3, 2, 3] = -1  # not seen
    vals[5, 1, :3] = 0  # exact origin: not seen
    scale = 0.1 if storage == "integer" else -0.1
    f = raw_c3d(tmp_path / f"{processor}_{storage}.c3d", vals, ["A", "B", "C", "D"], rate=50.0, scale=scale, processor=processor)
    a = read_c3d(f, engine="ezc3d")
    b = read_c3d(f, engine="numpy")
    expected = vals[..., :3] * (0.1 if storage == "integer" else 1.0)
    expected[3, 2] = np.nan
    expected[5, 1] = np.nan
    np.testing.assert_allclose(b.points, expected, rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(a.points, b.points)
    assert a.rate == b.rate == 50.0
    assert a.labels == ["A", "B", "C", "D"]
    assert b.info["processor"] == processor and b.info["storage"] == storage
    assert a.info["engine"] == ("numpy" if processor == "mips" else "ezc3d")  # ezc3d 1.7 refuses MIPS files
    assert read_c3d(f).info["engine"] == "numpy"  # the default


# --------------------------------------------------------------------------- bad input


@pytest.fixture()
def good_c3d(tmp_path: Path) -> Path:
    rng = np.random.default_rng(31)
    return ezc3d_file(tmp_path / "good.c3d", rng.normal(size=(40, 6, 3)) * 100 + 500, [f"M{i}" for i in range(6)])


def _expect_input_error(path: Path, match: str) -> InputError:
    with pytest.raises(InputError, match=match) as ei:
        read_markers(path)
    assert path.name in str(ei.value)
    assert ei.value.exit_code == 3
    assert "—" in str(ei.value)  # "what is wrong — what to do"
    return ei.value


def test_empty_c3d(tmp_path: Path) -> None:
    f = tmp_path / "empty.c3d"
    f.write_bytes(b"")
    _expect_input_error(f, "empty file")


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_random_bytes(tmp_path: Path, seed: int) -> None:
    rng = np.random.default_rng(seed)
    f = tmp_path / f"noise{seed}.c3d"
    f.write_bytes(rng.integers(0, 256, 3000, dtype=np.uint8).tobytes())
    _expect_input_error(f, "not a C3D file|damaged|truncated")


def test_random_bytes_behind_a_valid_first_word(tmp_path: Path) -> None:
    rng = np.random.default_rng(5)
    f = tmp_path / "noise.c3d"
    f.write_bytes(bytes([2, 0x50]) + rng.integers(0, 256, 3000, dtype=np.uint8).tobytes())
    _expect_input_error(f, "not a C3D file|damaged|truncated")


def test_text_file_named_c3d(tmp_path: Path) -> None:
    f = tmp_path / "notes.c3d"
    f.write_text("hello\n" * 200)
    _expect_input_error(f, "not a C3D file")


def test_cut_after_its_header(tmp_path: Path, good_c3d: Path) -> None:
    f = tmp_path / "cut.c3d"
    f.write_bytes(good_c3d.read_bytes()[:512])
    _expect_input_error(f, "truncated C3D file")


def test_cut_after_its_parameters(tmp_path: Path, good_c3d: Path) -> None:
    lay = read_layout(good_c3d)
    f = tmp_path / "params_only.c3d"
    f.write_bytes(good_c3d.read_bytes()[: (lay.data_start - 1) * 512])
    _expect_input_error(f, "before its first frame")


def test_truncated_inside_a_frame(tmp_path: Path, good_c3d: Path) -> None:
    b = good_c3d.read_bytes()
    lay = read_layout(good_c3d)
    f = tmp_path / "trunc.c3d"
    f.write_bytes(b[: (lay.data_start - 1) * 512 + 17 * lay.bytes_per_frame + 5])
    _expect_input_error(f, r"truncated C3D file \(17 of 40 frames")


def test_all_nan_c3d(tmp_path: Path) -> None:
    f = ezc3d_file(tmp_path / "nan.c3d", np.full((5, 2, 3), np.nan), ["A", "B"], residual=-np.ones((5, 2)))
    _expect_input_error(f, "no marker data")


def test_damaged_parameter_sections_never_crash_the_process(tmp_path: Path, good_c3d: Path) -> None:
    """ezc3d 1.7 segfaults or hangs on some damaged parameter sections: they must end as InputError or a read."""
    script = textwrap.dedent(
        f"""
        import numpy as np
        from pathlib import Path
        from mocapskel.errors import InputError
        from mocapskel.io.markers import read_markers
        src = Path({str(good_c3d)!r}).read_bytes()
        pstart = (src[0] - 1) * 512
        end = pstart + src[pstart + 2] * 512
        outcome = {{"ok": 0, "error": 0}}
        for seed in range(60):
            rng = np.random.default_rng(seed)
            b = bytearray(src)
            for i in rng.integers(pstart + 4, end, 20):
                b[i] = int(rng.integers(0, 256))
            f = Path({str(tmp_path)!r}) / f"fz{{seed}}.c3d"
            f.write_bytes(bytes(b))
            try:
                read_markers(f)
                outcome["ok"] += 1
            except InputError as e:
                assert f.name in str(e)
                outcome["error"] += 1
        print(outcome)
        """
    )
    repo = Path(__file__).resolve().parents[1]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(repo), os.environ.get("PYTHONPATH")]))}
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120, cwd=repo, env=env)
    assert r.returncode == 0, (r.returncode, r.stderr[-2000:])
    assert "'error'" in r.stdout


# --------------------------------------------------------------------------- what the fast read relies on


@pytest.mark.parametrize("storage", ["integer", "float"])
def test_ezc3d_itself_reads_negative_residuals_as_nan(tmp_path: Path, storage: str) -> None:
    """The ezc3d engine does not fetch residuals: ezc3d must already have set those points to NaN."""
    from ezc3d import ezc3d as swig

    vals = np.zeros((5, 2, 4))
    vals[..., :3] = np.arange(30).reshape(5, 2, 3) + 7.0
    vals[2, 1, 3] = -1  # coordinates present, residual negative
    f = raw_c3d(tmp_path / f"{storage}.c3d", vals, ["A", "B"], rate=50.0, scale=0.1 if storage == "integer" else -0.1)
    pts = swig.c3d(str(f)).get_points()[:3].transpose(2, 1, 0)
    assert np.isnan(pts[2, 1]).all()
    assert np.isfinite(np.delete(pts.reshape(-1, 3), 2 * 2 + 1, axis=0)).all()
    assert np.isnan(read_c3d(f, engine="ezc3d").points[2, 1]).all()


def test_fit_without_cache_does_not_hash_the_take(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from mocapskel import pipeline
    from mocapskel.cache import Cache

    rng = np.random.default_rng(3)
    a, b = tmp_path / "a.c3d", tmp_path / "b.c3d"
    write_markers(a, random_markers(rng, F=200, gaps=0.0))
    write_markers(b, random_markers(rng, F=200, gaps=0.0))
    key_a = pipeline.read_input(a, hash_content=False)[1]
    assert key_a == pipeline.read_input(a, hash_content=False)[1] != pipeline.read_input(b, hash_content=False)[1]
    assert key_a != pipeline.read_input(a, pipeline.ReadOptions(exclude=("MK00",)), hash_content=False)[1]

    def no_hash(*args, **kw):
        raise AssertionError("hashed without a cache")

    monkeypatch.setattr(pipeline, "file_key", no_hash)
    pipeline.run_until(a, "clean", cache=Cache(None))
    with pytest.raises(AssertionError, match="hashed"):
        pipeline.run_until(a, "clean", cache=Cache(tmp_path / "cache"))
    monkeypatch.undo()
    first = pipeline.run_until(a, "clean", cache=Cache(tmp_path / "cache"))
    again = pipeline.run_until(a, "clean", cache=Cache(tmp_path / "cache"))
    assert again.cached == ["clean"] and again.key == first.key


def test_computed_points_from_the_groups_type_groups_names_and_virtual_groups(tmp_path: Path) -> None:
    """``POINT:TYPE_GROUPS`` names the POINT parameters that list model outputs (Vicon): their labels are
    computed, as are those of a group named virtual or modelled; a group of markers it names is not."""
    xyz = np.ones((3, 5, 3))
    labels = ["LASI", "Knee1", "Mid", "RASI", "C7"]
    extra = {("POINT", "TYPE_GROUPS"): ["MARKERS", "BODYMODEL"], ("POINT", "BODYMODEL"): ["Knee1"],
             ("POINT", "MARKERS"): ["LASI", "RASI"], ("POINT", "VIRTUAL_MARKERS"): ["Mid"]}
    m = read_markers(ezc3d_file(tmp_path / "typed.c3d", xyz, labels, extra=extra))
    assert m.labels == ("LASI", "RASI", "C7")
    assert m.info["excluded_why"]["Knee1"] == "computed point: listed in POINT:BODYMODEL"
    assert m.info["excluded_why"]["Mid"] == "computed point: listed in POINT:VIRTUAL_MARKERS"
