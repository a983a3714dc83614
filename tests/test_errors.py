"""Bad input, odd files and degenerate data, through the command line (issue 6).

Every bad input ends in one line ``mocapskel: error: <file>: <what is wrong> —
<what to do>`` on stderr with the documented exit code (2 usage, 3 unreadable
or invalid input, 4 the data cannot support a skeleton), no traceback unless
``-v``, no output file (not even a temporary one) and the input untouched.
Readers are tested in ``test_io_*.py``; here every case goes through ``fit``
(or another command) as a user would run it.
"""
from __future__ import annotations

import hashlib
import json
import os
import struct
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import ezc3d
import numpy as np
import pytest
from click.testing import CliRunner, Result

from mocapskel.artifacts import Markers
from mocapskel.cli.main import cli
from mocapskel.io.bvh_read import read_bvh
from mocapskel.io.markers import write_markers
from mocapskel.synth.presets import Recipe, make

# --------------------------------------------------------------------------- helpers


def invoke(*args: object) -> Result:
    return CliRunner().invoke(cli, [str(a) for a in args])


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def assert_one_line_error(r: Result, code: int, *needles: str, name: str | None = None) -> str:
    """The run failed with ``code`` and one clean ``mocapskel: error:`` line; returns that line."""
    assert r.exit_code == code, f"exit {r.exit_code}, stderr:\n{r.stderr}"
    assert isinstance(r.exception, SystemExit), repr(r.exception)
    assert "Traceback" not in r.stderr
    errors = [ln for ln in r.stderr.splitlines() if ln.startswith("mocapskel: error:")]
    assert len(errors) == 1, r.stderr
    line = errors[0]
    assert r.stderr.rstrip().splitlines()[-1] == line, "the error line must be the last line"
    for n in needles:
        assert n in line, f"{n!r} not in {line!r}"
    if name is not None:
        assert f"{name}:" in line, f"the error line does not name {name}: {line!r}"
    if code != 2 or name is not None:  # click's own usage errors say what to do differently
        assert " — " in line, f"the error line does not say what to do: {line!r}"
    return line


def assert_nothing_written(folder: Path, *outputs: Path) -> None:
    for o in outputs:
        assert not o.exists(), f"{o} was written"
    left = [p.name for p in folder.iterdir() if p.name.endswith(".part") or ".part." in p.name]
    assert not left, f"temporary files left behind: {left}"


def fit_fails(tmp_path: Path, src: Path, code: int, *needles: str, name: str | None = None) -> str:
    """Run ``fit`` on ``src``: it must fail cleanly, write nothing and leave ``src`` as it was."""
    before = digest(src) if src.is_file() else None
    out, rep = tmp_path / "out.bvh", tmp_path / "out.json"
    r = invoke("fit", src, "-o", out, "--report", rep, "--no-cache")
    line = assert_one_line_error(r, code, *needles, name=src.name if name is None else name)
    assert_nothing_written(tmp_path, out, rep)
    if before is not None:
        assert digest(src) == before, "the input was modified"
    return line


def fit_ok(src: Path, out: Path, *extra: object) -> tuple[dict, Result]:
    rep = out.with_suffix(".json")
    r = invoke("fit", src, "-o", out, "--report", rep, "--no-cache", *extra)
    assert r.exit_code == 0, r.stderr
    assert "Traceback" not in r.stderr and "error:" not in r.stderr
    return json.loads(rep.read_text()), r


def bones(rep: dict) -> dict[tuple[str, ...], float]:
    """Bone lengths keyed by the marker labels of the segment (names may differ between fits)."""
    members = {s["name"]: tuple(sorted(s["markers"])) for s in rep["segments"]}
    return {members[b["segment"]]: b["length_mm"] for b in rep["bones"]}


def trc_text(labels: list[str], rows: list[list[str]], *, rate: float = 100.0, units: str = "mm") -> str:
    """A hand-written TRC (tab separated); ``rows`` are the coordinate fields of each frame."""
    head = (
        "PathFileType\t4\t(X/Y/Z)\thand.trc\n"
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames\n"
        f"{rate:g}\t{rate:g}\t{len(rows)}\t{len(labels)}\t{units}\t{rate:g}\t1\t{len(rows)}\n"
        "Frame#\tTime\t" + "\t\t\t".join(labels) + "\n"
        "\t\t" + "\t".join(f"X{i}\tY{i}\tZ{i}" for i in range(1, len(labels) + 1)) + "\n\n"
    )
    body = "".join(f"{i + 1}\t{i / rate:.5f}\t" + "\t".join(r) + "\n" for i, r in enumerate(rows))
    return head + body


def ezc3d_file(path: Path, xyz: np.ndarray, labels: list[str], *, rate: float = 120.0, units: str = "mm",
               residual: np.ndarray | None = None) -> Path:
    """A float C3D built by ezc3d; ``xyz`` (F, M, 3) in file units, written as given (zeros stay zeros)."""
    F, M = xyz.shape[:2]
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [rate]
    c["parameters"]["POINT"]["LABELS"]["value"] = list(labels)
    c["parameters"]["POINT"]["UNITS"]["value"] = [units]
    data = np.ones((4, M, F))
    data[:3] = xyz.transpose(2, 1, 0)
    c["data"]["points"] = data
    res = np.zeros((F, M)) if residual is None else residual
    c["data"]["meta_points"]["residuals"] = res.T[None].astype(float)
    c["data"]["meta_points"]["camera_masks"] = np.zeros((7, M, F), dtype=bool)
    c.write(str(path))
    return path


def integer_c3d(path: Path, xyz_mm: np.ndarray, labels: list[str], *, rate: float, scale: float) -> Path:
    """An integer (scaled) C3D written byte by byte: coordinates stored as round(mm / scale), gaps residual -1."""
    F, P = xyz_mm.shape[:2]
    seen = np.isfinite(xyz_mm).all(axis=2)
    words = np.zeros((F, P, 4))
    words[..., :3] = np.where(seen[..., None], np.round(np.nan_to_num(xyz_mm) / scale), 0.0)
    words[..., 3] = np.where(seen, 0.0, -1.0)
    assert np.abs(words).max() < 32767

    def i16(v: int) -> bytes:
        return struct.pack("<h", v)

    def param(gid: int, name: str, ptype: int, dims: tuple[int, ...], data: bytes, last: bool = False) -> bytes:
        body = struct.pack("b", ptype) + bytes([len(dims)]) + bytes(dims) + data + bytes([0])
        return struct.pack("b", len(name)) + struct.pack("b", gid) + name.encode() + i16(0 if last else len(body) + 2) + body

    def group(gid: int, name: str) -> bytes:
        return struct.pack("b", len(name)) + struct.pack("b", -gid) + name.encode() + i16(3) + bytes([0])

    width = max(len(s) for s in labels)
    recs = [
        group(1, "POINT"),
        param(1, "USED", 2, (), i16(P)),
        param(1, "FRAMES", 2, (), i16(F)),
        param(1, "SCALE", 4, (), struct.pack("<f", scale)),
        param(1, "RATE", 4, (), struct.pack("<f", rate)),
        param(1, "DATA_START", 2, (), i16(0)),  # patched below
        param(1, "LABELS", -1, (width, P), b"".join(s.encode().ljust(width) for s in labels)),
        param(1, "UNITS", -1, (2,), b"mm"),
        group(2, "ANALOG"),
        param(2, "USED", 2, (), i16(0)),
        param(2, "RATE", 4, (), struct.pack("<f", 0.0), last=True),
    ]
    body = b"".join(recs)
    nblocks = (4 + len(body)) // 512 + 1
    data_start = 2 + nblocks
    i = body.index(b"DATA_START") + len(b"DATA_START") + 4
    body = body[:i] + i16(data_start) + body[i + 2:]
    psec = (bytes([1, 0x50, nblocks, 84]) + body).ljust(nblocks * 512, b"\x00")
    head = bytes([2, 0x50]) + i16(P) + i16(0) + i16(1) + i16(F) + i16(0) + struct.pack("<f", scale)
    head = (head + i16(data_start) + i16(0) + struct.pack("<f", rate)).ljust(512, b"\x00")
    path.write_bytes(head + psec + words.astype("<i2").tobytes())
    return path


@pytest.fixture(scope="module")
def link() -> Markers:
    """Kirk's linkage (3 rods, 3 markers each), 0.5 mm noise, 5 s at 120 Hz."""
    return make(Recipe(kind="linkage", frames=600, noise_mm=0.5, seed=1)).markers


@pytest.fixture(scope="module")
def link_trc(tmp_path_factory, link: Markers) -> Path:
    p = tmp_path_factory.mktemp("link") / "link.trc"
    write_markers(p, link)
    return p


@pytest.fixture(scope="module")
def link_fit(tmp_path_factory, link_trc: Path) -> dict:
    """The report of a plain fit of the linkage (the reference for the variants below)."""
    rep, _ = fit_ok(link_trc, tmp_path_factory.mktemp("ref") / "ref.bvh")
    return rep


# --------------------------------------------------------------------------- unreadable or invalid files: exit 3


def test_empty_c3d_and_trc(tmp_path: Path) -> None:
    for name in ("empty.c3d", "empty.trc"):
        (tmp_path / name).write_bytes(b"")
        fit_fails(tmp_path, tmp_path / name, 3, "empty file")


@pytest.mark.parametrize("ext", [".c3d", ".trc"])
def test_random_bytes(tmp_path: Path, ext: str) -> None:
    f = tmp_path / f"noise{ext}"
    f.write_bytes(np.random.default_rng(11).integers(0, 256, 5000, dtype=np.uint8).tobytes())
    fit_fails(tmp_path, f, 3)


def test_truncated_c3d(tmp_path: Path, link: Markers) -> None:
    good = tmp_path / "good.c3d"
    write_markers(good, link)
    b = good.read_bytes()
    f = tmp_path / "trunc.c3d"
    f.write_bytes(b[: len(b) * 2 // 3 + 7])  # inside a frame
    fit_fails(tmp_path, f, 3, "truncated C3D file")


def test_c3d_cut_after_its_header(tmp_path: Path, link: Markers) -> None:
    good = tmp_path / "good.c3d"
    write_markers(good, link)
    f = tmp_path / "cut.c3d"
    f.write_bytes(good.read_bytes()[:512])
    fit_fails(tmp_path, f, 3, "C3D")


def test_text_file_that_is_not_a_trc(tmp_path: Path) -> None:
    f = tmp_path / "table.trc"
    f.write_text("frame,x,y,z\n1,0.1,0.2,0.3\n2,0.1,0.2,0.3\n")
    fit_fails(tmp_path, f, 3, "not a TRC file")


def test_trc_with_a_header_but_no_frames(tmp_path: Path) -> None:
    f = tmp_path / "header_only.trc"
    f.write_text(trc_text(["A", "B", "C"], []))
    fit_fails(tmp_path, f, 3, "no marker data")


def test_non_numeric_value_in_a_trc_names_its_line(tmp_path: Path) -> None:
    rows = [["1.0", "2.0", "3.0"] * 2 for _ in range(10)]
    rows[4][3] = "12,5"  # a decimal comma
    f = tmp_path / "comma.trc"
    f.write_text(trc_text(["A", "B"], rows))
    line = fit_fails(tmp_path, f, 3, "'12,5' is not a number", "line 11")
    assert "fix the value" in line


def test_all_coordinates_nan(tmp_path: Path, link: Markers) -> None:
    f = tmp_path / "allnan.trc"
    write_markers(f, replace(link, points=np.full_like(link.points, np.nan)))
    fit_fails(tmp_path, f, 3, "no marker data")


def test_all_coordinates_inf(tmp_path: Path) -> None:
    f = tmp_path / "allinf.trc"
    f.write_text(trc_text(["A", "B"], [["inf", "-inf", "inf"] * 2 for _ in range(200)]))
    fit_fails(tmp_path, f, 3, "no marker data")


def test_some_inf_values_are_read_as_gaps(tmp_path: Path, link: Markers) -> None:
    f = tmp_path / "someinf.trc"
    write_markers(f, link)
    lines = f.read_text().splitlines(keepends=True)
    for k in (50, 51, 300):  # data rows start on line 7 (index 6)
        fields = lines[6 + k].split("\t")
        fields[2:5] = ["inf", "-inf", "inf"]
        lines[6 + k] = "\t".join(fields)
    f.write_text("".join(lines))
    rep, r = fit_ok(f, tmp_path / "o.bvh")
    assert "3 samples with infinite coordinates read as gaps" in r.stderr
    assert rep["input"]["read"]["nonfinite"] == 3
    _, root_pos, _, _ = read_bvh(tmp_path / "o.bvh")
    assert root_pos.shape[0] == link.n_frames and np.isfinite(root_pos).all()


def test_trc_rows_with_missing_trailing_markers_are_gaps(tmp_path: Path, link: Markers) -> None:
    """Some exporters stop a row after the last marker seen: the rest of the row is a gap, not an error."""
    f = tmp_path / "short_rows.trc"
    write_markers(f, link)
    lines = f.read_text().splitlines(keepends=True)
    short = range(100, 140)
    for k in short:
        fields = lines[6 + k].rstrip("\n").split("\t")
        lines[6 + k] = "\t".join(fields[: 2 + 3 * 7]) + "\n"  # markers 8 and 9 left out
    f.write_text("".join(lines))
    rep, _ = fit_ok(f, tmp_path / "o.bvh")
    assert rep["input"]["frames"] == link.n_frames
    assert rep["input"]["read"]["gaps_fraction"] == pytest.approx(2 * len(short) / (link.n_frames * 9))
    _, root_pos, _, _ = read_bvh(tmp_path / "o.bvh")
    assert root_pos.shape[0] == link.n_frames


@pytest.mark.parametrize("name", ["take.csv", "take.bvh", "take"])
def test_unknown_extension(tmp_path: Path, link_trc: Path, name: str) -> None:
    f = tmp_path / name
    f.write_bytes(link_trc.read_bytes())
    fit_fails(tmp_path, f, 3, "unknown marker file type", "give a .c3d or .trc file")


def test_missing_file(tmp_path: Path) -> None:
    fit_fails(tmp_path, tmp_path / "nowhere.c3d", 3, "no such file")


def test_a_folder_as_input(tmp_path: Path) -> None:
    d = tmp_path / "takes.c3d"
    d.mkdir()
    fit_fails(tmp_path, d, 3, "folder")


@pytest.mark.parametrize("kind", ["fifo", "device"])
def test_a_pipe_or_a_device_as_input_is_refused_without_hanging(tmp_path: Path, kind: str) -> None:
    """A named pipe with no writer, or a link to /dev/zero: reading either would never end (a real process, with a timeout)."""
    f = tmp_path / "take.c3d"
    if kind == "fifo":
        os.mkfifo(f)
    else:
        f.symlink_to("/dev/zero")
    r = subprocess.run(
        [sys.executable, "-m", "mocapskel", "fit", str(f), "-o", str(tmp_path / "o.bvh")],
        capture_output=True, text=True, timeout=60, env=dict(os.environ, XDG_CACHE_HOME=str(tmp_path / "cache")),
    )
    assert r.returncode == 3, r.stderr
    assert r.stderr.strip().splitlines()[-1] == f"mocapskel: error: {f}: not a regular file — give a .c3d or .trc file"
    assert_nothing_written(tmp_path, tmp_path / "o.bvh")


def test_damaged_artifact(tmp_path: Path) -> None:
    f = tmp_path / "seg.npz"
    f.write_bytes(b"PK\x03\x04 not really a zip")
    before = digest(f)
    r = invoke("ik", f, "-o", tmp_path / "ik.npz", "--no-cache")
    assert_one_line_error(r, 3, name="seg.npz")
    assert_nothing_written(tmp_path, tmp_path / "ik.npz")
    assert digest(f) == before


@pytest.mark.parametrize("command", ["inspect", "segment"])
def test_other_commands_give_the_same_error(tmp_path: Path, command: str) -> None:
    f = tmp_path / "empty.trc"
    f.write_bytes(b"")
    args = [command, f] if command == "inspect" else [command, f, "-o", tmp_path / "s.npz", "--no-cache"]
    assert_one_line_error(invoke(*args), 3, "empty file", name="empty.trc")
    assert_nothing_written(tmp_path, tmp_path / "s.npz")


def test_traceback_only_with_verbose(tmp_path: Path) -> None:
    f = tmp_path / "empty.c3d"
    f.write_bytes(b"")
    r = invoke("fit", f, "-o", tmp_path / "o.bvh", "--no-cache", "-v")
    assert r.exit_code == 3
    assert "Traceback" in r.stderr and "InputError" in r.stderr
    assert r.stderr.rstrip().splitlines()[-1].startswith("mocapskel: error: ")


# --------------------------------------------------------------------------- usage: exit 2


def test_output_folder_that_does_not_exist(tmp_path: Path, link_trc: Path) -> None:
    out = tmp_path / "nodir" / "o.bvh"
    r = invoke("fit", link_trc, "-o", out, "--no-cache")
    assert_one_line_error(r, 2, "does not exist")
    assert not out.parent.exists()


def test_output_under_a_regular_file(tmp_path: Path, link_trc: Path) -> None:
    (tmp_path / "file.txt").write_text("keep me\n")
    out = tmp_path / "file.txt" / "out.bvh"
    r = invoke("fit", link_trc, "-o", out, "--no-cache")
    assert_one_line_error(r, 2, "does not exist")
    assert (tmp_path / "file.txt").read_text() == "keep me\n"


def test_report_under_a_regular_file(tmp_path: Path, link_trc: Path) -> None:
    (tmp_path / "file.txt").write_text("keep me\n")
    r = invoke("fit", link_trc, "-o", tmp_path / "o.bvh", "--report", tmp_path / "file.txt" / "r.json", "--no-cache")
    assert_one_line_error(r, 2, "does not exist")
    assert_nothing_written(tmp_path, tmp_path / "o.bvh")


@pytest.mark.skipif(os.geteuid() == 0, reason="running as root: root can write into a read-only folder, so it cannot be tested here")
def test_output_folder_not_writable(tmp_path: Path, link_trc: Path) -> None:
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        assert_one_line_error(invoke("fit", link_trc, "-o", ro / "o.bvh", "--no-cache"), 2, "not writable")
    finally:
        ro.chmod(0o700)
    assert not any(ro.iterdir())


def test_output_is_the_input(tmp_path: Path, link_trc: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    f = tmp_path / "take.trc"
    f.write_bytes(link_trc.read_bytes())
    before = digest(f)
    link = tmp_path / "alias.trc"
    link.symlink_to(f)
    monkeypatch.chdir(tmp_path)  # the input given as a relative path, the output spelt differently
    for out_args in (["-o", f], ["-o", "./take.trc"], ["-o", link], ["-o", tmp_path / "o.bvh", "--report", f]):
        r = invoke("fit", "take.trc", *out_args, "--no-cache")
        assert_one_line_error(r, 2, "is the input")
    assert digest(f) == before
    assert_nothing_written(tmp_path, tmp_path / "o.bvh")


# --------------------------------------------------------------------------- too little data: exit 4


def test_one_marker(tmp_path: Path, link: Markers) -> None:
    f = tmp_path / "one.trc"
    write_markers(f, replace(link, points=link.points[:, :1], labels=link.labels[:1]))
    fit_fails(tmp_path, f, 4, "only 1 marker")


@pytest.mark.parametrize("frames", [1, 2])
def test_one_or_two_frames(tmp_path: Path, link: Markers, frames: int) -> None:
    f = tmp_path / f"f{frames}.c3d"
    write_markers(f, replace(link, points=link.points[:frames]))
    fit_fails(tmp_path, f, 4, "too short")


@pytest.mark.parametrize("segments", [10, 50])
def test_more_segments_than_markers(tmp_path: Path, link_trc: Path, segments: int) -> None:
    """Regression: --segments above the marker count crashed in the eigen-gap (IndexError, exit 1)."""
    r = invoke("fit", link_trc, "-o", tmp_path / "o.bvh", "--no-cache", "--segments", segments)
    assert_one_line_error(r, 4, f"asked for {segments} segments but only 9 markers", name=link_trc.name)
    assert_nothing_written(tmp_path, tmp_path / "o.bvh")


def test_rest_frame_outside_the_take(tmp_path: Path, link_trc: Path) -> None:
    r = invoke("fit", link_trc, "-o", tmp_path / "o.bvh", "--no-cache", "--rest-frame", 5000)
    assert_nothing_written(tmp_path, tmp_path / "o.bvh")
    assert_one_line_error(r, 4, "rest frame 5000", name=link_trc.name)


def test_one_rigid_body(tmp_path: Path) -> None:
    """Twelve markers on one moving, turning body: nothing moves relative to anything."""
    rng = np.random.default_rng(4)
    local = rng.normal(size=(12, 3)) * 150.0
    F = 600
    t = np.arange(F) / 120.0
    ang = np.stack([np.sin(1.3 * t), 0.7 * np.cos(0.9 * t), 0.5 * t], axis=1)
    from scipy.spatial.transform import Rotation

    R = Rotation.from_rotvec(ang).as_matrix()
    pts = np.einsum("fij,mj->fmi", R, local) + (np.array([0, 0, 1000.0]) + 300 * np.sin(t)[:, None])[:, None, :]
    pts += rng.normal(0, 0.5, pts.shape)
    f = tmp_path / "box.c3d"
    write_markers(f, Markers(points=pts, labels=tuple(f"B{i}" for i in range(12)), rate=120.0))
    line = fit_fails(tmp_path, f, 4, "one rigid body")
    assert "nothing moves relative to anything" in line


# --------------------------------------------------------------------------- C3D variety through fit


def test_integer_c3d_fits_like_the_float_one(tmp_path: Path, link: Markers, link_fit: dict) -> None:
    f = integer_c3d(tmp_path / "int.c3d", link.points, list(link.labels), rate=link.rate, scale=0.1)
    rep, _ = fit_ok(f, tmp_path / "int.bvh")
    assert rep["input"]["read"].get("storage") == "integer"
    got, ref = bones(rep), bones(link_fit)
    assert got.keys() == ref.keys()
    for k, v in ref.items():  # 0.1 mm quantisation against 0.5 mm noise
        assert got[k] == pytest.approx(v, rel=2e-3, abs=0.5), k


def test_units_m_cm_mm_give_the_same_skeleton(tmp_path: Path, link: Markers) -> None:
    """The same take stored in m, cm and mm (values exact in float32 in all three) fits to the same bones."""
    q = 2.0 ** -14  # metres: x * 100 and x * 1000 stay exact in float32 for |x| < 4 m
    metres = np.round(link.points / 1000.0 / q) * q
    reps, offsets = {}, {}
    for units, k in (("m", 1.0), ("cm", 100.0), ("mm", 1000.0)):
        f = ezc3d_file(tmp_path / f"take_{units}.c3d", metres * k, list(link.labels), rate=link.rate, units=units)
        reps[units], _ = fit_ok(f, tmp_path / f"take_{units}.bvh")
        skel, root_pos, _, _ = read_bvh(tmp_path / f"take_{units}.bvh")
        offsets[units] = (np.asarray(skel.offset), root_pos)
        assert reps[units]["input"]["source_units"] == units
    ref = bones(reps["mm"])
    for units in ("m", "cm"):
        got = bones(reps[units])
        assert got.keys() == ref.keys()
        for key, v in ref.items():
            assert got[key] == pytest.approx(v, rel=1e-6), (units, key)
        np.testing.assert_allclose(offsets[units][0], offsets["mm"][0], rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose(offsets[units][1], offsets["mm"][1], rtol=1e-6, atol=1e-6)


def test_zeros_mean_missing(tmp_path: Path, link: Markers) -> None:
    """Gaps stored as (0, 0, 0) with a valid residual fit exactly like the same gaps stored as NaN."""
    rng = np.random.default_rng(2)
    pts = link.points.copy()
    for m in range(pts.shape[1]):
        s = int(rng.integers(50, 500))
        pts[s : s + 40, m] = np.nan
    nan_file = tmp_path / "nan.c3d"
    write_markers(nan_file, replace(link, points=pts))
    zero_file = ezc3d_file(tmp_path / "zero.c3d", np.nan_to_num(pts, nan=0.0), list(link.labels), rate=link.rate)
    a, _ = fit_ok(nan_file, tmp_path / "nan.bvh")
    b, _ = fit_ok(zero_file, tmp_path / "zero.bvh")
    assert a["input"]["read"]["gaps_fraction"] > 0
    assert b["input"]["read"]["gaps_fraction"] == pytest.approx(a["input"]["read"]["gaps_fraction"])
    assert bones(a) == bones(b)


@pytest.fixture(scope="module")
def with_computed(tmp_path_factory, link: Markers) -> Path:
    """The linkage plus points a capture program computes: joint centres and an angle."""
    pts = link.points
    extra = np.stack(
        [pts[:, 0:3].mean(axis=1), pts[:, 3:6].mean(axis=1), np.degrees(np.arctan2(pts[:, 6], 1000.0))], axis=1
    )
    labels = list(link.labels) + ["LHJC", "RKJC", "LKneeAngles"]
    f = tmp_path_factory.mktemp("computed") / "computed.c3d"
    write_markers(f, replace(link, points=np.concatenate([pts, extra], axis=1), labels=tuple(labels)))
    return f


def test_computed_points_are_left_out(tmp_path: Path, with_computed: Path, link: Markers) -> None:
    plain = tmp_path / "plain.c3d"
    write_markers(plain, link)
    ref, _ = fit_ok(plain, tmp_path / "p.bvh")
    rep, _ = fit_ok(with_computed, tmp_path / "c.bvh")
    assert rep["input"]["markers"] == link.n_markers
    assert set(rep["input"]["read"]["excluded"]) == {"LHJC", "RKJC", "LKneeAngles"}
    used = {m for s in rep["segments"] for m in s["markers"]}
    assert not used & {"LHJC", "RKJC", "LKneeAngles"}
    assert bones(rep) == bones(ref)


def test_exclude_and_include(tmp_path: Path, with_computed: Path, link: Markers) -> None:
    rep, _ = fit_ok(with_computed, tmp_path / "e.bvh", "--exclude", "rod3_c")
    assert rep["input"]["markers"] == link.n_markers - 1
    assert "rod3_c" in rep["input"]["read"]["excluded"]
    rep, _ = fit_ok(with_computed, tmp_path / "i.bvh", "--include", "rod1_*", "--include", "rod2_*")
    assert rep["input"]["markers"] == 6
    assert {m for s in rep["segments"] for m in s["markers"]} <= {f"rod{i}_{c}" for i in (1, 2) for c in "abc"}
    # an include pattern that names a computed point keeps it
    rep, _ = fit_ok(with_computed, tmp_path / "k.bvh", "--include", "rod*", "--include", "LHJC")
    assert rep["input"]["markers"] == link.n_markers + 1 and "LHJC" not in rep["input"]["read"]["excluded"]
    # patterns that leave nothing: invalid input, said clearly
    r = invoke("fit", with_computed, "-o", tmp_path / "n.bvh", "--no-cache", "--include", "nothing*")
    assert_one_line_error(r, 3, "no marker data left", name=with_computed.name)
    assert_nothing_written(tmp_path, tmp_path / "n.bvh")


def test_header_frame_count_and_rate_that_disagree_with_the_data(tmp_path: Path, link: Markers) -> None:
    f = tmp_path / "liar.c3d"
    write_markers(f, link)
    b = bytearray(f.read_bytes())
    b[8:10] = struct.pack("<H", 100)  # header: last frame 100 (the data has 600)
    b[20:24] = struct.pack("<f", 60.0)  # header: 60 Hz (POINT:RATE says 120)
    f.write_bytes(bytes(b))
    rep, r = fit_ok(f, tmp_path / "o.bvh")
    _, root_pos, _, frame_time = read_bvh(tmp_path / "o.bvh")
    assert root_pos.shape[0] == link.n_frames == rep["input"]["frames"]
    assert frame_time == pytest.approx(1 / 120.0)
    assert "header frame range 100" in r.stderr and "header rate 60" in r.stderr


# --------------------------------------------------------------------------- degenerate data


def _two_rods(F: int, *, collinear: bool, rng: np.random.Generator) -> Markers:
    """Two rods joined by a ball joint; each rod's 3 markers lie on its own axis when ``collinear``."""
    from scipy.spatial.transform import Rotation

    t = np.arange(F) / 120.0
    R0 = Rotation.from_rotvec(np.stack([0.4 * np.sin(0.7 * t), 0.3 * np.cos(0.5 * t), 0.6 * np.sin(0.3 * t)], 1)).as_matrix()
    R1 = R0 @ Rotation.from_rotvec(np.stack([0.9 * np.sin(2.1 * t), 0.8 * np.cos(1.7 * t), 0.7 * np.sin(1.1 * t + 1)], 1)).as_matrix()
    o0 = np.array([0.0, 0.0, 1000.0]) + 50 * np.stack([np.sin(t), np.cos(t), 0 * t], 1)
    along = np.array([[80.0, 0, 0], [180.0, 0, 0], [260.0, 0, 0]])
    off = np.zeros((3, 3)) if collinear else rng.normal(size=(3, 3)) * 40.0
    a = o0[:, None] + np.einsum("fij,mj->fmi", R0, along - np.array([300.0, 0, 0]) + off)
    b = o0[:, None] + np.einsum("fij,mj->fmi", R1, along + off[::-1])
    pts = np.concatenate([a, b], axis=1) + rng.normal(0, 0.3, (F, 6, 3))
    return Markers(points=pts, labels=("A1", "A2", "A3", "B1", "B2", "B3"), rate=120.0)


def test_collinear_markers_fit_or_say_why(tmp_path: Path) -> None:
    f = tmp_path / "collinear.c3d"
    write_markers(f, _two_rods(900, collinear=True, rng=np.random.default_rng(8)))
    r = invoke("fit", f, "-o", tmp_path / "o.bvh", "--report", tmp_path / "o.json", "--no-cache")
    if r.exit_code == 0:
        _, root_pos, local_rot, _ = read_bvh(tmp_path / "o.bvh")
        assert root_pos.shape[0] == 900 and np.isfinite(root_pos).all()
    else:
        assert_one_line_error(r, 4, name=f.name)
        assert_nothing_written(tmp_path, tmp_path / "o.bvh", tmp_path / "o.json")


@pytest.mark.parametrize("lost", [(300, 360), (0, 120), (700, 800)], ids=["middle", "start", "end"])
def test_every_marker_lost_for_a_stretch(tmp_path: Path, lost: tuple[int, int]) -> None:
    """Up to a second with no marker at all (middle, start, end): fit still works and outputs every frame."""
    from mocapskel.synth.corrupt import everything_lost

    take = make(Recipe(kind="chain", counts=(4, 3, 3), frames=800, noise_mm=0.3, seed=5))
    take = everything_lost(take, lost)
    assert np.isnan(take.markers.points[lost[0] : lost[1]]).all()
    f = tmp_path / "lost.trc"
    write_markers(f, take.markers)
    r = invoke("fit", f, "-o", tmp_path / "o.bvh", "--report", tmp_path / "o.json", "--no-cache")
    if r.exit_code != 0:
        assert_one_line_error(r, 4, name=f.name)
        return
    _, root_pos, local_rot, _ = read_bvh(tmp_path / "o.bvh")
    assert root_pos.shape[0] == 800
    assert np.isfinite(root_pos).all() and np.isfinite(local_rot).all()


def test_every_marker_lost_for_the_whole_take_but_one_frame(tmp_path: Path, link: Markers) -> None:
    pts = np.full_like(link.points, np.nan)
    pts[10] = link.points[10]
    f = tmp_path / "one_frame_seen.trc"
    write_markers(f, replace(link, points=pts))
    fit_fails(tmp_path, f, 4)


def _three_segments_one_frozen(F: int, rng: np.random.Generator, wiggle_deg: float) -> Markers:
    """A chain A–B–C, 4 markers each: A–B exercised in all directions, B–C turning at most ``wiggle_deg`` about each axis."""
    from scipy.spatial.transform import Rotation

    t = np.arange(F) / 120.0
    RA = Rotation.from_rotvec(np.stack([0.5 * np.sin(0.6 * t), 0.4 * np.cos(0.4 * t), 0.8 * np.sin(0.25 * t)], 1)).as_matrix()
    RB = RA @ Rotation.from_rotvec(np.stack([0.9 * np.sin(1.9 * t), 0.8 * np.cos(1.3 * t + 0.3), 0.7 * np.sin(1.1 * t)], 1)).as_matrix()
    w = np.radians(wiggle_deg) * np.stack([np.sin(0.8 * t), np.cos(0.6 * t), np.sin(1.1 * t + 0.5)], 1)
    RC = RB @ Rotation.from_rotvec(w).as_matrix()
    oA = np.array([0.0, 0, 1000]) + 100 * np.stack([np.sin(0.5 * t), np.cos(0.3 * t), 0.2 * np.sin(t)], 1)
    oB = oA + np.einsum("fij,j->fi", RA, [300.0, 0, 0])
    oC = oB + np.einsum("fij,j->fi", RB, [300.0, 0, 0])
    loc = [rng.normal(size=(4, 3)) * 50 + [150.0, 0, 0] for _ in range(3)]
    pts = np.concatenate(
        [o[:, None] + np.einsum("fij,mj->fmi", R, lc) for o, R, lc in ((oA, RA, loc[0]), (oB, RB, loc[1]), (oC, RC, loc[2]))],
        axis=1,
    ) + rng.normal(0, 0.3, (F, 12, 3))
    return Markers(points=pts, labels=tuple(f"{s}{i}" for s in "ABC" for i in range(4)), rate=120.0)


def test_a_joint_that_is_never_exercised_is_warned_about(tmp_path: Path) -> None:
    f = tmp_path / "frozen.c3d"
    write_markers(f, _three_segments_one_frozen(1200, np.random.default_rng(9), wiggle_deg=0.5))
    rep, r = fit_ok(f, tmp_path / "o.bvh", "--segments", "3")
    name = {s["markers"][0][0]: s["name"] for s in rep["segments"]}  # segment of the A*, B*, C* markers
    assert {(j["parent"], j["child"]) for j in rep["joints"]} == {(name["B"], name["A"]), (name["B"], name["C"])}
    warned = [w for w in rep["warnings"] if "poorly determined" in w]
    assert len(warned) == 1 and name["B"] in warned[0] and name["C"] in warned[0], rep["warnings"]
    assert "poorly determined" in r.stderr


def test_absurd_coordinates_are_refused(tmp_path: Path) -> None:
    """Points far beyond any capture volume (a units mix-up or garbage) are bad input, not a crash."""
    from mocapskel.synth.presets import Recipe, make

    take = make(Recipe(kind="linkage", frames=600, noise_mm=0.5, seed=3))
    from dataclasses import replace as _replace

    f = tmp_path / "huge.trc"
    write_markers(f, _replace(take.markers, points=take.markers.points * 1e12))
    r = invoke("fit", f, "-o", tmp_path / "o.bvh", "--no-cache")
    assert_nothing_written(tmp_path, tmp_path / "o.bvh")
    assert_one_line_error(r, 3, "beyond any capture volume", name=f.name)


@pytest.mark.parametrize("stop, code, word", [("Interrupted", 130, "interrupted"), ("Terminated", 143, "terminated")])
def test_a_signal_that_python_wrapped_in_another_error_still_ends_in_its_code(
        tmp_path: Path, link_trc: Path, monkeypatch, stop: str, code: int, word: str) -> None:
    """Python 3.11 turns an exception raised while a class is created (a dataclass's field, during a lazy
    import) into a RuntimeError caused by it: a Ctrl-C or SIGTERM that lands then ends in 130 / 143 with
    one line, as any other (a SIGINT sent 0.3 s into a fit, in one run of the test suite, came out as an
    unexpected RuntimeError, exit 1)."""
    from mocapskel import pipeline
    from mocapskel.cli import main as cli_main

    def wrapped(*args, **kwargs):
        try:
            raise getattr(cli_main, stop)()
        except BaseException as e:
            raise RuntimeError("Error calling __set_name__ on 'Field' instance 'computed' in 'RawTake'") from e

    monkeypatch.setattr(pipeline, "fit", wrapped)
    out = tmp_path / "o.bvh"
    r = invoke("fit", link_trc, "-o", out)
    assert_one_line_error(r, code, f"{word} — no output was written")
    assert not out.exists()
    monkeypatch.setattr(pipeline, "fit", lambda *a, **k: (_ for _ in ()).throw(RuntimeError("something else")))
    assert_one_line_error(invoke("fit", link_trc, "-o", out), 1, "unexpected RuntimeError: something else")


@pytest.mark.parametrize("handler, code, word", [("_on_sigint", 130, "interrupted"), ("_on_sigterm", 143, "terminated")])
def test_a_signal_that_a_library_swallowed_still_ends_the_run(
        tmp_path: Path, link_trc: Path, monkeypatch, handler: str, code: int, word: str) -> None:
    """A library's bare ``except:`` running when the signal came (a module being imported) swallows the exception
    the handler raised: the run still ends in 130 / 143 with one line and no output (a SIGTERM 0.3 s into a fit,
    in one run of the test suite, let the fit run to its end and exit 0)."""
    import signal as _signal

    from mocapskel import pipeline
    from mocapskel.cli import main as cli_main

    real = pipeline.fit

    def swallowed(*args, **kwargs):
        try:
            getattr(cli_main, handler)(_signal.SIGINT if handler == "_on_sigint" else _signal.SIGTERM, None)
        except BaseException:  # what a bare except in a library does
            pass
        return real(*args, **kwargs)

    monkeypatch.setattr(pipeline, "fit", swallowed)
    out = tmp_path / "o.bvh"
    r = invoke("fit", link_trc, "-o", out, "--report", tmp_path / "o.json", "--no-cache")
    assert_one_line_error(r, code, f"{word} — no output was written")
    assert_nothing_written(tmp_path, out)
    assert not (tmp_path / "o.json").exists()
    monkeypatch.setattr(pipeline, "fit", real)
    assert invoke("fit", link_trc, "-o", out, "--no-cache").exit_code == 0  # nothing held against the next run
