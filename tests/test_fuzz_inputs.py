"""Hypothesis fuzz of every reader and loader through the command line.

Generated C3D headers and parameters, TRC headers, ``.npz`` artifacts with
arrays swapped for generated ones, ``.skel`` and report JSON with fields swapped
for generated JSON values. Whatever the input, the command ends with exit 0,
2, 3 or 4 — never 1 (a bug) — and a failure is one line
``mocapskel: error: <file>: ... — <what to do>``.

Example counts are small (the whole module takes a few seconds);
MOCAPSKEL_HYPOTHESIS_SCALE=20 runs 20 times as many.
"""
from __future__ import annotations

import json
import os
import struct
import tempfile
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner, Result
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import array_shapes, arrays

from mocapskel import artifacts
from mocapskel.cli.main import cli
from mocapskel.io.markers import write_markers
from mocapskel.synth.presets import Recipe, make

from test_io_c3d import raw_c3d
from mocapskel.io import artifact_files

SCALE = max(1, int(os.environ.get("MOCAPSKEL_HYPOTHESIS_SCALE", "1")))
FUZZ = settings(max_examples=15 * SCALE, deadline=None, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])

_TMP = tempfile.TemporaryDirectory(prefix="mocapskel-fuzz-")
TMP = Path(_TMP.name)


def invoke(*args: object) -> Result:
    return CliRunner().invoke(cli, [str(a) for a in args])


def assert_clean_end(r: Result, allowed: tuple[int, ...] = (0, 2, 3, 4)) -> None:
    """Exit 0, or a documented code with one error line that says what to do; never 1, never a traceback."""
    assert r.exit_code in allowed, f"exit {r.exit_code}: {r.stderr}\n{r.exception!r}"
    assert isinstance(r.exception, (SystemExit, type(None))), repr(r.exception)
    assert "Traceback" not in r.stderr
    if r.exit_code:
        errors = [ln for ln in r.stderr.splitlines() if ln.startswith("mocapskel: error:")]
        assert len(errors) == 1, r.stderr
        assert r.stderr.rstrip().splitlines()[-1] == errors[0]
        assert " — " in errors[0], errors[0]


# --------------------------------------------------------------------------- seeds: genuine files


@pytest.fixture(scope="module")
def genuine() -> dict[str, Path]:
    """A small take and what the pipeline makes of it: motion artifact, skeleton file, report."""
    d = TMP / "genuine"
    d.mkdir(exist_ok=True)
    take = d / "link.trc"
    write_markers(take, make(Recipe(kind="linkage", frames=240, noise_mm=0.5, seed=3)).markers)
    r = invoke("fit", take, "-o", d / "o.bvh", "--report", d / "o.json", "--skeleton-out", d / "s.skel", "--no-cache", "-q")
    assert r.exit_code == 0, r.stderr
    r = invoke("ik", take, "-o", d / "m.npz", "--no-cache", "-q")
    assert r.exit_code == 0, r.stderr
    return {"take": take, "motion": d / "m.npz", "skel": d / "s.skel", "report": d / "o.json"}


# --------------------------------------------------------------------------- strategies

odd_floats = st.one_of(
    st.sampled_from([0.0, -0.0, 0.5, 1.0, 100.0, 1e5, 1e6, 1e9, 1e30, 3.4e38, float("inf"), float("-inf"), float("nan")]),
    st.floats(width=32),
)
json_values = st.recursive(
    st.one_of(st.none(), st.booleans(), st.integers(-10**12, 10**12), st.floats(allow_nan=False), st.text(max_size=8)),
    lambda inner: st.one_of(st.lists(inner, max_size=4), st.dictionaries(st.text(max_size=6), inner, max_size=4)),
    max_leaves=12,
)


# --------------------------------------------------------------------------- C3D headers and parameters


_GENUINE_FRAMES, _GENUINE_POINTS = 20, 3


def _genuine_c3d(name: str, seed: int) -> tuple[Path, bytearray]:
    """A small genuine float C3D (20 frames, points A, B, C, 100 Hz) in the fuzz folder, and its bytes to alter."""
    rng = np.random.default_rng(seed)
    F, P = _GENUINE_FRAMES, _GENUINE_POINTS
    vals = np.concatenate([rng.normal(size=(F, P, 3)) * 300 + 1000, np.zeros((F, P, 1))], axis=2)
    f = TMP / f"{name}.c3d"
    raw_c3d(f, vals, ["A", "B", "C"], rate=100.0, scale=-1.0)
    return f, bytearray(f.read_bytes())


@FUZZ
@given(rate=odd_floats, scale=odd_floats, frames=st.integers(0, 65535), points=st.integers(0, 40),
       data=st.data())
def test_c3d_with_generated_header_values(rate: float, scale: float, frames: int, points: int, data) -> None:
    """POINT:RATE/SCALE/USED/FRAMES and the header's words as generated, over a small genuine data block."""
    f, b = _genuine_c3d("gen", seed=0)
    # header: word 2 points, words 4/5 first/last frame, float at 12 scale, float at 20 rate
    struct.pack_into("<H", b, 2, points)
    struct.pack_into("<H", b, 8, frames)
    struct.pack_into("<f", b, 12, scale)
    struct.pack_into("<f", b, 20, rate)
    # the parameters of the same name, found by their names
    for name, fmt, value in ((b"RATE", "<f", rate), (b"SCALE", "<f", scale), (b"USED", "<h", min(points, 32767)),
                             (b"FRAMES", "<h", frames - 65536 if frames > 32767 else frames)):
        i = b.find(name, 512)
        if i > 0 and data.draw(st.booleans(), label=f"patch {name.decode()}"):
            struct.pack_into(fmt, b, i + len(name) + 2 + 2, value)  # offset word, type byte, ndims byte
    f.write_bytes(bytes(b))
    assert_clean_end(invoke("inspect", f), allowed=(0, 3))


@pytest.mark.parametrize("scale", [float("inf"), float("-inf"), float("nan")])
def test_c3d_whose_point_scale_is_not_a_number_is_refused(scale: float) -> None:
    # found by the test above: an infinite POINT:SCALE made integer data 0 x inf (exit 1, a RuntimeWarning)
    f, b = _genuine_c3d("scale", seed=0)
    struct.pack_into("<f", b, 12, scale)
    i = b.find(b"SCALE", 512)
    struct.pack_into("<f", b, i + len(b"SCALE") + 2 + 2, scale)
    f.write_bytes(bytes(b))
    for cmd in ("inspect", "fit"):
        r = invoke(cmd, f) if cmd == "inspect" else invoke(cmd, f, "-o", str(TMP / "scale.bvh"))
        assert r.exit_code == 3, r.stderr
        assert "POINT:SCALE" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    assert not (TMP / "scale.bvh").exists()


def test_c3d_with_a_signalling_nan_coordinate_reads_it_as_not_seen() -> None:
    # found by the byte fuzz test below: a float32 signalling NaN in the data block raised a RuntimeWarning on
    # its cast to float64 (exit 1)
    f, b = _genuine_c3d("snan", seed=1)
    F, P = _GENUINE_FRAMES, _GENUINE_POINTS
    start = (struct.unpack_from("<H", b, 16)[0] - 1) * 512  # header word 9: the data block's first 512-byte block
    frame, point = 5, 1
    struct.pack_into("<I", b, start + (frame * P + point) * 16, 0x7F800001)  # x of B in frame 5: a signalling NaN
    f.write_bytes(bytes(b))
    r = invoke("inspect", f)
    assert r.exit_code == 0, r.stderr
    from mocapskel.io.markers import read_markers

    pts = read_markers(f).points
    assert not np.isfinite(pts[frame, point]).all() and np.isfinite(np.delete(pts.reshape(F * P, 3), frame * P + point, 0)).all()


@FUZZ
@given(values=st.lists(st.tuples(st.integers(0, 2000), st.binary(min_size=1, max_size=4)), min_size=1, max_size=6))
def test_c3d_with_generated_bytes_in_its_header_and_parameters(values) -> None:
    f, b = _genuine_c3d("bytes", seed=1)
    for pos, chunk in values:
        pos = pos % (len(b) - len(chunk))
        b[pos:pos + len(chunk)] = chunk
    f.write_bytes(bytes(b))
    assert_clean_end(invoke("inspect", f), allowed=(0, 3))


# --------------------------------------------------------------------------- TRC headers

header_field = st.one_of(st.sampled_from(["100", "120.5", "0", "-1", "inf", "-inf", "nan", "1e300", "1e9", "", "mm", "m", "x"]),
                         odd_floats.map(repr), st.text(alphabet="0123456789.e-+ab", max_size=8))


@FUZZ
@given(fields=st.lists(header_field, min_size=8, max_size=8), names=st.integers(0, 5), time_step=odd_floats,
       rows=st.integers(0, 6))
def test_trc_with_generated_header(fields: list[str], names: int, time_step: float, rows: int) -> None:
    """DataRate, CameraRate, NumFrames, NumMarkers, Units … as generated; Time column steps as generated."""
    M = 3
    head = ("PathFileType\t4\t(X/Y/Z)\tgen.trc\n"
            "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames\n"
            + "\t".join(f.replace("\t", " ").replace("\n", " ") for f in fields) + "\n"
            "Frame#\tTime\t" + "".join(f"M{i}\t\t\t" for i in range(names)).rstrip("\t") + "\n"
            "\t\t" + "\t".join(f"X{i}\tY{i}\tZ{i}" for i in range(1, M + 1)) + "\n\n")
    rng = np.random.default_rng(2)
    body = "".join(
        f"{k + 1}\t{k * time_step!r}\t" + "\t".join(f"{v:.3f}" for v in rng.normal(size=3 * M) * 300) + "\n"
        for k in range(rows))
    f = TMP / "gen.trc"
    f.write_text(head + body)
    assert_clean_end(invoke("inspect", f), allowed=(0, 3))


# --------------------------------------------------------------------------- .npz artifacts

dtypes = st.sampled_from([np.float64, np.float32, np.int64, np.int8, np.bool_, np.dtype("<U3")])


@st.composite
def generated_arrays(draw) -> np.ndarray:
    dt = np.dtype(draw(dtypes))
    shape = draw(array_shapes(min_dims=0, max_dims=4, min_side=0, max_side=4))
    if dt.kind == "f":
        elements = st.floats(width=32 if dt == np.float32 else 64)
    elif dt.kind == "U":
        # numpy's fixed-width strings drop trailing NULs, which hypothesis refuses to generate into them
        elements = st.text(st.characters(codec="utf-8", exclude_characters="\x00"), max_size=3)
    else:
        elements = None
    return draw(arrays(dt, shape, elements=elements))


@FUZZ
@given(data=st.data())
def test_artifact_with_generated_arrays(genuine: dict[str, Path], data) -> None:
    """Some of a genuine motion artifact's arrays replaced by generated arrays (any dtype, shape, value), removed,
    or kept with their shape and generated values: inspect and export end cleanly."""
    arrs = artifact_files.read_arrays(genuine["motion"])
    keys = sorted(arrs)
    for key in data.draw(st.lists(st.sampled_from(keys), min_size=1, max_size=3, unique=True), label="keys"):
        how = data.draw(st.sampled_from(["replace", "remove", "same shape"]), label=f"how {key}")
        if how == "remove":
            del arrs[key]
        elif how == "same shape" and arrs[key].dtype.kind == "f":
            arrs[key] = data.draw(arrays(arrs[key].dtype, arrs[key].shape, elements=odd_floats.map(float)), label=key)
        else:
            arrs[key] = data.draw(generated_arrays(), label=key)
    f = TMP / "gen.npz"
    f.write_bytes(artifacts.arrays_bytes(arrs))
    assert_clean_end(invoke("inspect", f), allowed=(0, 3))
    assert_clean_end(invoke("export", f, "-o", TMP / "gen.bvh", "--no-cache"))


@pytest.mark.parametrize("names", [["", "00", "0"], ["Hip", "Hips", "Knee"]])
def test_an_artifact_whose_segment_names_no_bvh_can_hold_is_damaged(genuine: dict[str, Path], names) -> None:
    """Segment names the pipeline never makes (empty, a leading digit, one the prefix of another): the artifact is
    reported damaged (exit 3) by export, not an unexpected error (found by the fuzz above)."""
    arrs = artifact_files.read_arrays(genuine["motion"])
    n = len(arrs["skeleton/names__strs__"])
    arrs["skeleton/names__strs__"] = np.array((names * n)[:n] if n > 3 else names[:n])
    f = TMP / "names.npz"
    f.write_bytes(artifacts.arrays_bytes(arrs))
    r = invoke("export", f, "-o", TMP / "names.bvh", "--no-cache")
    assert_clean_end(r)
    assert r.exit_code == 3 and "damaged mocapskel artifact" in r.stderr and "skeleton.names" in r.stderr, r.stderr
    assert not (TMP / "names.bvh").exists()


@FUZZ
@given(info=json_values, where=st.sampled_from(["info__json__", "skeleton/info__json__",
                                                 "skeleton/joints/topology/segments/markers/info__json__",
                                                 "skeleton/joints/topology/segments/info__json__",
                                                 "skeleton/joints/info__json__"]))
def test_artifact_with_generated_info(genuine: dict[str, Path], info, where: str) -> None:
    arrs = artifact_files.read_arrays(genuine["motion"])
    arrs[where] = np.array(json.dumps(info))
    f = TMP / "info.npz"
    f.write_bytes(artifacts.arrays_bytes(arrs))
    assert_clean_end(invoke("inspect", f), allowed=(0, 3))
    assert_clean_end(invoke("export", f, "-o", TMP / "info.bvh", "--no-cache"))


# --------------------------------------------------------------------------- JSON: skeleton files, reports


def _paths(doc, prefix=()):
    """Every place in a JSON document (dict keys and list indices), for replacing one."""
    yield prefix
    if isinstance(doc, dict):
        for k, v in doc.items():
            yield from _paths(v, prefix + (k,))
    elif isinstance(doc, list):
        for i, v in enumerate(doc[:3]):
            yield from _paths(v, prefix + (i,))


def _replace(doc, path, value):
    if not path:
        return value
    d = doc
    for k in path[:-1]:
        d = d[k]
    d[path[-1]] = value
    return doc


@FUZZ
@given(data=st.data())
def test_skeleton_file_with_generated_json(genuine: dict[str, Path], data) -> None:
    doc = json.loads(genuine["skel"].read_text())
    places = list(_paths(doc))
    for _ in range(data.draw(st.integers(1, 3), label="edits")):
        path = data.draw(st.sampled_from(places), label="where")
        try:
            doc = _replace(doc, path, data.draw(json_values, label="value"))
        except (KeyError, IndexError, TypeError):  # an earlier edit removed the place
            pass
    f = TMP / "gen.skel"
    f.write_text(json.dumps(doc))
    assert_clean_end(invoke("solve", genuine["take"], "--skeleton", f, "-o", TMP / "solve.bvh", "-q"))


@FUZZ
@given(data=st.data())
def test_report_with_generated_json(genuine: dict[str, Path], data) -> None:
    doc = json.loads(genuine["report"].read_text())
    small = {"bones": doc["bones"], "segments": doc["segments"]}
    places = [p for p in _paths(small)]
    for _ in range(data.draw(st.integers(1, 3), label="edits")):
        path = data.draw(st.sampled_from(places), label="where")
        try:
            small = _replace(small, path, data.draw(json_values, label="value"))
        except (KeyError, IndexError, TypeError):
            pass
    f = TMP / "gen.json"
    f.write_text(json.dumps(small))
    assert_clean_end(invoke("compare", genuine["report"], f), allowed=(0, 3))


# --------------------------------------------------------------------------- BVH

bvh_tokens = st.one_of(st.sampled_from(["{", "}", "ROOT", "JOINT", "End", "Site", "OFFSET", "CHANNELS", "0", "3", "6",
                                        "Xrotation", "Frames:", "Frame", "Time:", "MOTION", "HIERARCHY", "nan", "-1",
                                        "1e400", ""]),
                       odd_floats.map(repr), st.text(alphabet="0123456789.-e", max_size=6))


@FUZZ
@given(data=st.data())
def test_bvh_with_generated_tokens(genuine: dict[str, Path], data) -> None:
    lines = (genuine["take"].parent / "o.bvh").read_text().split("\n")[:200]
    lines[lines.index("MOTION") + 1] = f"Frames: {len([ln for ln in lines[lines.index('MOTION') + 3:] if ln.strip()])}"
    for _ in range(data.draw(st.integers(1, 4), label="edits")):
        i = data.draw(st.integers(0, len(lines) - 1), label="line")
        toks = lines[i].split() or [""]
        j = data.draw(st.integers(0, len(toks) - 1), label="token")
        toks[j] = data.draw(bvh_tokens, label="new token")
        lines[i] = " ".join(toks)
    f = TMP / "gen.bvh"
    f.write_text("\n".join(lines) + "\n")
    assert_clean_end(invoke("inspect", f), allowed=(0, 3))
