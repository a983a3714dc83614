"""Odd inputs beyond the usual ones, each a regression test named after the case.

Every case ends in its documented exit code (2 usage, 3 bad input, 4 the data
cannot support a skeleton; never 1, never a hang) and one line
``mocapskel: error: <file>: <what is wrong> — <what to do>``. Also: a cache
whose entries are swapped, cut or bit-flipped recovers; output names of any
legal length; SIGTERM / SIGINT at several moments of a fit.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner, Result

from mocapskel import artifacts
from mocapskel.artifacts import Markers
from mocapskel.cache import Cache, digest
from mocapskel.cli.main import cli
from mocapskel.io import artifact_files
from mocapskel.io.bvh_read import read_bvh
from mocapskel.io.markers import read_markers, write_markers
from mocapskel.synth.presets import Recipe, make

from test_io_c3d import _long_take, ezc3d_file, raw_c3d

STAGES = ("clean", "merge-ids", "segment", "topology", "joints", "rigid", "ik")


def invoke(*args: object) -> Result:
    return CliRunner().invoke(cli, [str(a) for a in args])


def one_line_error(r: Result, code: int, *needles: str, name: str | None = None) -> str:
    """The run failed with ``code`` and exactly one ``mocapskel: error:`` line that says what to do."""
    assert r.exit_code == code, f"exit {r.exit_code}, stderr:\n{r.stderr}"
    assert isinstance(r.exception, SystemExit), repr(r.exception)
    assert "Traceback" not in r.stderr
    errors = [ln for ln in r.stderr.splitlines() if ln.startswith("mocapskel: error:")]
    assert len(errors) == 1, r.stderr
    line = errors[0]
    assert r.stderr.rstrip().splitlines()[-1] == line
    assert " — " in line, f"the error does not say what to do: {line!r}"
    for n in needles:
        assert n in line, f"{n!r} not in {line!r}"
    if name is not None:
        assert f"{name}:" in line, line
    return line


def run_process(*args: object, timeout: float = 60, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "mocapskel", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout, cwd=cwd, env=dict(os.environ, PYTHONWARNINGS="ignore"))


@pytest.fixture(scope="module")
def link() -> Markers:
    return make(Recipe(kind="linkage", frames=600, noise_mm=0.5, seed=1)).markers


@pytest.fixture(scope="module")
def link_trc(tmp_path_factory, link: Markers) -> Path:
    p = tmp_path_factory.mktemp("link") / "link.trc"
    write_markers(p, link)
    return p


@pytest.fixture(scope="module")
def motion_npz(tmp_path_factory, link_trc: Path) -> Path:
    p = tmp_path_factory.mktemp("ik") / "motion.npz"
    r = invoke("ik", link_trc, "-o", p, "--no-cache", "-q")
    assert r.exit_code == 0, r.stderr
    return p


@pytest.fixture(scope="module")
def skel_file(tmp_path_factory, link_trc: Path) -> Path:
    d = tmp_path_factory.mktemp("skel")
    r = invoke("fit", link_trc, "-o", d / "o.bvh", "--skeleton-out", d / "s.skel", "--report", d / "o.json", "--no-cache", "-q")
    assert r.exit_code == 0, r.stderr
    return d / "s.skel"


# --------------------------------------------------------------------------- absurd rates


ABSURD_RATES = [float("inf"), 1e6, 1e9, 1e300, float(np.finfo(np.float32).max), float(np.finfo(np.float64).max), 0.5]


@pytest.mark.parametrize("rate", ABSURD_RATES, ids=lambda r: f"{r:g}")
def test_c3d_with_an_absurd_rate_is_refused(tmp_path: Path, link: Markers, rate: float) -> None:
    """POINT:RATE and the header's rate inf, 1e6, 1e9, 1e300 (inf in float32), the largest floats, 0.5 Hz."""
    vals = np.concatenate([np.nan_to_num(link.points[:50, :4]), np.zeros((50, 4, 1))], axis=2)
    with np.errstate(over="ignore"):
        r32 = float(np.float32(rate))  # as a C3D stores it: 1e300 and the largest double are inf
    f = raw_c3d(tmp_path / "rate.c3d", vals, list(link.labels[:4]), rate=r32, scale=-1.0)
    line = one_line_error(invoke("fit", f, "-o", tmp_path / "o.bvh", "--no-cache"), 3, "not a capture rate", name="rate.c3d")
    assert "POINT:RATE" in line
    assert not (tmp_path / "o.bvh").exists()


@pytest.mark.parametrize("rate", ["inf", "1e6", "1e9", "1e300", "1.7976931348623157e308", "0.5", "-inf"])
def test_trc_with_an_absurd_rate_is_refused(tmp_path: Path, link: Markers, rate: str) -> None:
    f = tmp_path / "rate.trc"
    write_markers(f, replace(link, points=link.points[:50]))
    lines = f.read_text().split("\n")
    vals = lines[2].split("\t")
    vals[0] = vals[1] = vals[5] = rate  # DataRate, CameraRate, OrigDataRate
    lines[2] = "\t".join(vals)
    f.write_text("\n".join(lines))
    if rate == "-inf":  # not a rate at all: the rate comes from the Time column (100 Hz here), as before
        assert read_markers(f).rate == pytest.approx(link.rate, rel=1e-3)
        return
    one_line_error(invoke("inspect", f), 3, "DataRate", "not a capture rate", name="rate.trc")


def test_trc_whose_time_column_gives_an_absurd_rate_is_refused(tmp_path: Path, link: Markers) -> None:
    f = tmp_path / "time.trc"
    write_markers(f, replace(link, points=link.points[:50], rate=2e5))  # Time column steps of 5 µs
    lines = f.read_text().split("\n")
    vals = lines[2].split("\t")
    vals[0] = vals[1] = "n/a"
    lines[2] = "\t".join(vals)
    f.write_text("\n".join(lines))
    one_line_error(invoke("inspect", f), 3, "Time column", "not a capture rate", name="time.trc")


# --------------------------------------------------------------------------- a cut long C3D


@pytest.mark.parametrize("saturated", [True, False])
def test_cut_long_c3d_ending_inside_its_last_frame_is_refused(tmp_path: Path, saturated: bool) -> None:
    """70,001 frames, data cut inside the last frame: with a 16-bit frame count saturated at 65535 (ezc3d's own
    file) the count cannot tell, the cut frame does; with POINT:LONG_FRAMES the count tells."""
    F = 70_001
    xyz = _long_take(F)
    f = tmp_path / "long.c3d"
    if saturated:
        ezc3d_file(f, xyz, ["A", "B"], rate=200.0)
    else:
        write_markers(f, Markers(points=xyz, labels=("A", "B"), rate=200.0))
    from mocapskel.io.c3d_layout import read_layout

    lay = read_layout(f)
    assert lay.declared_frames()[2] is saturated
    end = (lay.data_start - 1) * 512 + F * lay.bytes_per_frame
    data = f.read_bytes()
    f.write_bytes(data[: end - lay.bytes_per_frame // 2])  # half of the last frame is gone
    one_line_error(invoke("inspect", f), 3, "truncated C3D file", name="long.c3d")


def test_uncut_long_c3d_with_a_saturated_count_still_reads_whole(tmp_path: Path) -> None:
    F = 70_001
    xyz = _long_take(F)
    f = ezc3d_file(tmp_path / "long.c3d", xyz, ["A", "B"], rate=200.0)
    m = read_markers(f)
    assert m.n_frames == F
    np.testing.assert_array_equal(m.points, xyz)


# --------------------------------------------------------------------------- crafted artifacts


def _craft(src: Path, dst: Path, **changes) -> Path:
    """A copy of an artifact with some arrays replaced (None: removed)."""
    data = artifact_files.read_arrays(src)
    for k, v in changes.items():
        k = k.replace("__S__", "/")
        if v is None:
            data.pop(k, None)
        else:
            data[k] = np.asarray(v)
    dst.write_bytes(artifacts.arrays_bytes(data))
    return dst


def _mk(path: str) -> str:
    """The key of a field of the markers inside a motion artifact."""
    return "skeleton/joints/topology/segments/markers/" + path


CRAFTED = {
    "schema_text": ({"__schema__": "one"}, "schema"),
    "schema_empty": ({"__schema__": np.zeros(0)}, "schema"),
    "points_2d": ({_mk("points"): np.zeros((600, 27))}, "points has shape"),
    "points_integer": ({_mk("points"): np.zeros((600, 9, 3), dtype=int)}, "points holds int"),
    "rate_text": ({_mk("rate"): "fast"}, "rate is a str"),
    "rate_zero": ({_mk("rate"): 0.0}, "not a capture rate"),
    "rate_nan": ({_mk("rate"): np.nan}, "not a capture rate"),
    "unknown_stage": ({_mk("stage"): "fit"}, "stage 'fit'"),
    "unknown_kind": ({"__kind__": "banana"}, "unknown artifact kind"),
    "labels_fewer_than_markers": ({_mk("labels__strs__"): np.array(["a", "b"])}, "labels has 2 entries for 9"),
    "offsets_1e300": ({"skeleton/origin": np.full((3, 3), 1e300)}, "origin holds values up to 1e+300"),
    "parent_cycle": ({"skeleton/parent": np.array([1, 0, -1])}, "cycle"),
    "self_parent": ({"skeleton/parent": np.array([0, -1, 1])}, "cycle"),
    "rotations_text": ({"rot": np.full((600, 3, 3, 3), "x")}, "rot holds"),
    "info_not_an_object": ({"info__json__": "[1, 2]"}, "info is not a JSON object"),
    "info_not_json": ({"info__json__": "{oops"}, "JSONDecodeError"),
    "rest_frame_outside": ({"skeleton/rest_frame": 10**9}, "rest_frame"),
    "motion_frames_mismatch": ({"root_pos": np.zeros((7, 3))}, "motion of 7 frames"),
}


@pytest.mark.parametrize("case", list(CRAFTED))
def test_crafted_artifact_is_refused_by_every_command(tmp_path: Path, motion_npz: Path, case: str) -> None:
    """Text or empty schema, 2-D or integer points, a text or zero rate, unknown stage or kind, labels that do
    not match the points, offsets of 1e300, parent cycles, ...: exit 3 from inspect and from a stage command."""
    changes, needle = CRAFTED[case]
    f = _craft(motion_npz, tmp_path / f"{case}.npz", **changes)
    one_line_error(invoke("inspect", f), 3, needle, name=f.name)
    one_line_error(invoke("export", f, "-o", tmp_path / "o.bvh", "--no-cache"), 3, needle, name=f.name)
    assert not (tmp_path / "o.bvh").exists()


def test_crafted_artifact_of_another_schema_or_not_an_archive(tmp_path: Path, motion_npz: Path) -> None:
    f = _craft(motion_npz, tmp_path / "s9.npz", __schema__=9)
    one_line_error(invoke("inspect", f), 3, "schema 9", name="s9.npz")
    g = tmp_path / "single.npz"
    with open(g, "wb") as fh:
        np.save(fh, np.zeros(3))
    one_line_error(invoke("inspect", g), 3, "not a readable mocapskel artifact", name="single.npz")


def test_genuine_artifacts_of_every_stage_still_load(tmp_path: Path, link_trc: Path) -> None:
    for s in STAGES:
        r = invoke(s, link_trc, "-o", tmp_path / f"{s}.npz", "--no-cache", "-q")
        assert r.exit_code == 0, r.stderr
        obj = artifact_files.load(tmp_path / f"{s}.npz")
        assert obj.kind == ("markers" if s in ("clean", "merge-ids") else artifacts.ARTIFACT_TYPES[obj.kind].kind)
        r = invoke("inspect", tmp_path / f"{s}.npz")
        assert r.exit_code == 0, r.stderr


# --------------------------------------------------------------------------- crafted skeleton files


def _skel_variant(src: Path, dst: Path, edit) -> Path:
    doc = json.loads(src.read_text())
    edit(doc)
    dst.write_text(json.dumps(doc))
    return dst


def _set(path: tuple, value):
    def edit(doc):
        d = doc
        for k in path[:-1]:
            d = d[k]
        d[path[-1]] = value
    return edit


def _cycle(doc):
    segs = doc["segments"]
    root = next(s for s in segs if s["parent"] is None)
    others = [s for s in segs if s is not root]
    others[0]["parent"], others[1]["parent"] = others[1]["name"], others[0]["name"]


def _self_parent(doc):
    s = next(s for s in doc["segments"] if s["parent"] is not None)
    s["parent"] = s["name"]


def _rename(i: int, new):
    """Segment ``i`` renamed everywhere (its parent links and its markers) to ``new(old names)``."""
    def edit(d):
        old = d["segments"][i]["name"]
        name = new([s["name"] for s in d["segments"]])
        for s in d["segments"]:
            s["name"] = name if s["name"] == old else s["name"]
            s["parent"] = name if s.get("parent") == old else s.get("parent")
        for m in d["markers"]:
            m["segment"] = name if m["segment"] == old else m["segment"]
    return edit


SKELS = {
    "rest_frame_text": (_set(("rest_frame",), "first"), "rest_frame"),
    "rest_frame_null": (_set(("rest_frame",), None), "rest_frame"),
    "rest_frame_negative": (_set(("rest_frame",), -3), "rest_frame"),
    "parent_cycle": (_cycle, "form a cycle"),
    "self_parent": (_self_parent, "form a cycle"),
    "offset_1e300": (_set(("segments", 0, "origin"), [1e300, 0, 0]), "beyond"),
    "marker_offset_text": (_set(("markers", 0, "local"), ["a", 0, 0]), "not a number"),
    "bone_length_text": (_set(("segments", 0, "bone_length"), "long"), "not a number"),
    "segments_not_a_list": (_set(("segments",), {"a": 1}), "lists of objects"),
    "version_true": (_set(("version",), True), "version"),
    "repeated_names": (lambda d: d["segments"][1].update(name=d["segments"][0]["name"]), "repeated segment names"),
    # names 'solve' would write into the BVH as they are
    "name_leading_digit": (_rename(0, lambda names: "0" + names[0]), "invalid BVH joint names"),
    "name_prefix_of_another": (_rename(1, lambda names: names[0] + "x"), "is a prefix of"),
    "name_with_a_space": (_rename(0, lambda names: "left hip"), "invalid BVH joint names"),
}


@pytest.mark.parametrize("case", list(SKELS))
def test_crafted_skeleton_file_is_refused(tmp_path: Path, skel_file: Path, link_trc: Path, case: str) -> None:
    edit, needle = SKELS[case]
    f = _skel_variant(skel_file, tmp_path / f"{case}.skel", edit)
    r = invoke("solve", link_trc, "--skeleton", f, "-o", tmp_path / "o.bvh")
    one_line_error(r, 3, needle, name=f.name)
    assert not (tmp_path / "o.bvh").exists()


def test_genuine_skeleton_file_still_solves(tmp_path: Path, skel_file: Path, link_trc: Path) -> None:
    r = invoke("solve", link_trc, "--skeleton", skel_file, "-o", tmp_path / "o.bvh", "-q")
    assert r.exit_code == 0, r.stderr
    assert read_bvh(tmp_path / "o.bvh")[1].shape[0] == 600


# --------------------------------------------------------------------------- compare reports


@pytest.mark.parametrize("value", ["long", [1, 2], True, -5.0, 1e300])
def test_compare_report_whose_bone_length_is_not_a_length(tmp_path: Path, skel_file: Path, value) -> None:
    rep = json.loads((skel_file.parent / "o.json").read_text())
    rep["bones"][0]["length_mm"] = value
    f = tmp_path / "bad.json"
    f.write_text(json.dumps(rep))
    one_line_error(invoke("compare", skel_file.parent / "o.json", f), 3, "bone length", name="bad.json")


def test_compare_report_whose_segments_are_not_a_list(tmp_path: Path, skel_file: Path) -> None:
    rep = json.loads((skel_file.parent / "o.json").read_text())
    rep["segments"] = 5
    f = tmp_path / "odd.json"
    f.write_text(json.dumps(rep))
    r = invoke("compare", skel_file.parent / "o.json", f)
    assert r.exit_code == 0, r.stderr  # the labels are optional: bones are matched by the tree
    assert "same subject: likely" in r.stdout


# --------------------------------------------------------------------------- synth parameters


@pytest.mark.parametrize("args", [
    ("--link-length", "-5"), ("--link-length", "nan"), ("--link-length", "inf"), ("--counts", "50-50"),
    ("--counts", "3"), ("--rate", "nan"), ("--rate", "1e9"), ("--noise", "inf"), ("--frames", "100000000"),
], ids=lambda a: " ".join(a))
def test_synth_chain_with_bad_parameters_is_a_usage_error(tmp_path: Path, args: tuple[str, str]) -> None:
    r = invoke("synth", "chain", "-o", tmp_path / "c.trc", "--frames", "50", *args)
    assert r.exit_code == 2, r.stderr
    assert "Traceback" not in r.stderr and r.stderr.strip().count("\n") == 0, r.stderr
    assert r.stderr.startswith("mocapskel: error: Invalid value for") and args[0] in r.stderr
    assert not list(tmp_path.iterdir())


# --------------------------------------------------------------------------- non-regular files


@pytest.mark.parametrize("command", ["solve --skeleton", "compare", "inspect npz", "inspect bvh", "inspect skel-less",
                                     "export", "fit"])
def test_a_fifo_as_any_file_argument_is_refused_without_hanging(tmp_path: Path, link_trc: Path, command: str) -> None:
    """A named pipe with no writer blocks whoever opens it: every file argument is checked before it is opened."""
    fifo = tmp_path / {"solve --skeleton": "s.skel", "compare": "r.json", "inspect npz": "a.npz", "inspect bvh": "a.bvh",
                       "inspect skel-less": "a.c3d", "export": "a.npz", "fit": "a.trc"}[command]
    os.mkfifo(fifo)
    args = {
        "solve --skeleton": ("solve", link_trc, "--skeleton", fifo, "-o", tmp_path / "o.bvh"),
        "compare": ("compare", fifo, fifo),
        "inspect npz": ("inspect", fifo), "inspect bvh": ("inspect", fifo), "inspect skel-less": ("inspect", fifo),
        "export": ("export", fifo, "-o", tmp_path / "o.bvh", "--no-cache"),
        "fit": ("fit", fifo, "-o", tmp_path / "o.bvh", "--no-cache"),
    }[command]
    r = run_process(*args, timeout=60)
    assert r.returncode == 3, r.stderr
    last = r.stderr.strip().splitlines()[-1]
    assert last.startswith(f"mocapskel: error: {fifo}: not a regular file — give "), last


def test_a_device_as_skeleton_is_refused(tmp_path: Path, link_trc: Path) -> None:
    dev = tmp_path / "zero.skel"
    dev.symlink_to("/dev/zero")
    r = run_process("solve", link_trc, "--skeleton", dev, "-o", tmp_path / "o.bvh")
    assert r.returncode == 3 and "not a regular file" in r.stderr, r.stderr


# --------------------------------------------------------------------------- the cache


def _fit(src: Path, out: Path, cache: Path) -> Result:
    r = invoke("fit", src, "-o", out, "--cache-dir", cache)
    assert r.exit_code == 0, r.stderr
    return r


@pytest.mark.parametrize("damage", ["swapped", "truncated", "bit_flipped", "key_edited"])
def test_cache_recovers_from_damaged_entries(tmp_path: Path, link_trc: Path, damage: str) -> None:
    """Swapped entries once made every later run fail (RecursionError); now each is found out by its key or
    checksum, deleted, recomputed and warned about, and the output is the same."""
    cache = tmp_path / "cache"
    _fit(link_trc, tmp_path / "a.bvh", cache)
    entries = sorted(cache.glob("*.npz"))
    assert len(entries) == len(STAGES)
    rng = np.random.default_rng(0)
    if damage == "swapped":
        for a, b in zip(entries[0::2], entries[1::2]):
            da, db = a.read_bytes(), b.read_bytes()
            a.write_bytes(db)
            b.write_bytes(da)
    else:
        for e in entries:
            b = bytearray(e.read_bytes())
            if damage == "truncated":
                b = b[: len(b) - 100]
            elif damage == "bit_flipped":  # one bit inside the data of the largest member
                i = int(rng.integers(len(b) // 4, len(b) // 2))
                b[i] ^= 1 << int(rng.integers(8))
            else:  # a valid archive whose stored key is another entry's
                data = artifact_files.read_arrays(e)
                data["__cache_key__"] = np.array("0" * 64)
                b = artifacts.arrays_bytes(data)
            e.write_bytes(bytes(b))
    r = _fit(link_trc, tmp_path / "b.bvh", cache)
    assert "deleted and recomputed" in r.stderr
    assert "Traceback" not in r.stderr
    assert (tmp_path / "a.bvh").read_bytes() == (tmp_path / "b.bvh").read_bytes()
    r = _fit(link_trc, tmp_path / "c.bvh", cache)  # repaired
    assert "deleted" not in r.stderr
    assert all(f"{s:9s} cached — skipping" in r.stderr for s in STAGES)


def test_cache_entry_that_refers_to_itself_is_discarded_not_followed(tmp_path: Path, motion_npz: Path) -> None:
    """An entry whose key and checksum are right but whose upstream reference names itself (or a loop of
    entries): the chain is followed in a loop that notices the repeat, never by recursion."""
    c = Cache(tmp_path / "cache")
    obj = artifact_files.load(motion_npz)
    for k1, k2 in (("a" * 64, "a" * 64), ("b" * 64, "c" * 64)):
        for key, ref in ((k1, k2), (k2, k1)):
            data = artifacts.to_arrays(obj, refs={id(obj.skeleton): ref})
            data["__cache_key__"] = np.array(key)
            data["__cache_digest__"] = np.array(digest(data))
            (c.folder / f"{key}.npz").write_bytes(artifacts.arrays_bytes(data))
        assert c.get(k1, "ik") is None
        assert any("refers back to itself" in w for w in c.warnings)
        assert not (c.folder / f"{k2}.npz").exists()  # the entry whose reference closes the loop


# --------------------------------------------------------------------------- long names


@pytest.mark.parametrize("length", [240, 250, 255])
def test_output_names_up_to_255_bytes(tmp_path: Path, link_trc: Path, length: int) -> None:
    """``-o`` with a 250-byte name once failed: the temporary ``.NAME.*.part`` passed the 255-byte limit."""
    bvh = tmp_path / ("b" * (length - 4) + ".bvh")
    rep = tmp_path / ("é" * ((length - 5) // 2) + "r" * ((length - 5) % 2) + ".json")  # two bytes a character
    c3d = tmp_path / ("m" * (length - 4) + ".c3d")  # ezc3d appends .c3d to a temporary name
    assert len(os.fsencode(bvh.name)) == len(os.fsencode(rep.name)) == len(os.fsencode(c3d.name)) == length
    r = invoke("fit", link_trc, "-o", bvh, "--report", rep, "--markers-out", c3d, "--no-cache")
    assert r.exit_code == 0, r.stderr
    assert read_bvh(bvh)[1].shape[0] == 600
    assert json.loads(rep.read_text())["input"]["frames"] == 600
    assert read_markers(c3d).n_frames == 600
    assert not [p.name for p in tmp_path.iterdir() if ".part" in p.name]


# --------------------------------------------------------------------------- what is wrong with the take


def _subset(link: Markers, idx: list[int]) -> Markers:
    return replace(link, points=link.points[:, idx], labels=tuple(link.labels[i] for i in idx))


@pytest.mark.parametrize("case", ["2_markers", "3_markers_one_per_segment", "flat_in_z", "one_marker_per_segment",
                                  "nothing_moves"])
def test_take_that_cannot_make_a_skeleton_says_why(tmp_path: Path, link: Markers, case: str) -> None:
    """Every marker is seen in every frame: the message is about the take, not 'never seen together'."""
    if case == "2_markers":
        mk, needle = _subset(link, [0, 3]), "only 2 markers are seen"
    elif case == "3_markers_one_per_segment":
        mk, needle = _subset(link, [0, 3, 6]), "every segment carries a single marker (3 segments)"
    elif case == "flat_in_z":
        p = link.points.copy()
        p[..., 2] = 5.0
        mk, needle = replace(link, points=p), "the take is flat"
    elif case == "one_marker_per_segment":
        mk, needle = make(Recipe(kind="chain", counts=(1, 1, 1, 1), frames=600, seed=2)).markers, "every segment carries a single marker (4 segments)"
    else:
        mk, needle = replace(link, points=np.repeat(link.points[:1], 600, axis=0)), "nothing moves"
    f = tmp_path / f"{case}.trc"
    write_markers(f, mk)
    line = one_line_error(invoke("fit", f, "-o", tmp_path / "o.bvh", "--no-cache"), 4, needle, name=f.name)
    assert "never seen together" not in line


def test_two_markers_on_two_segments_of_a_chain_say_why(tmp_path: Path) -> None:
    mk = make(Recipe(kind="chain", counts=(1, 1), frames=600, seed=2)).markers
    f = tmp_path / "c11.trc"
    write_markers(f, mk)
    one_line_error(invoke("fit", f, "-o", tmp_path / "o.bvh", "--no-cache"), 4, "only 2 markers are seen", name="c11.trc")


def test_three_markers_that_can_make_a_skeleton_still_do(tmp_path: Path) -> None:
    """2 + 1 markers on two segments: enough for a joint (the checks above only explain failures)."""
    mk = make(Recipe(kind="chain", counts=(2, 1), frames=600, seed=2)).markers
    f = tmp_path / "c21.trc"
    write_markers(f, mk)
    r = invoke("fit", f, "-o", tmp_path / "o.bvh", "--no-cache", "-q")
    assert r.exit_code == 0, r.stderr
    assert len(read_bvh(tmp_path / "o.bvh")[0].names) == 2


# --------------------------------------------------------------------------- signals


def _handlers_installed(pid: int) -> bool:
    """Whether the process catches SIGTERM (Python does not by default: mocapskel's first instruction does)."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return False
    caught = int(next(ln.split()[1] for ln in status.splitlines() if ln.startswith("SigCgt:")), 16)
    return bool(caught & (1 << (signal.SIGTERM - 1)))


@pytest.fixture(scope="module")
def medium(tmp_path_factory) -> Path:
    """A take that fits for several seconds (3 min of the 48-marker human at 120 Hz)."""
    p = tmp_path_factory.mktemp("medium") / "human.c3d"
    r = invoke("synth", "human", "-o", p, "--frames", 20000, "--seed", 5, "-q")
    assert r.exit_code == 0, r.stderr
    return p


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="needs /proc to see when the handlers are installed")
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
@pytest.mark.parametrize("moment", ["first_instruction", "0.3s", "0.8s", "1.5s"])
def test_signal_at_several_moments_of_a_fit(tmp_path: Path, medium: Path, sig: int, moment: str) -> None:
    """From the command's first instruction on, SIGTERM ends in 143 and SIGINT in 130 with one line and no output
    (a SIGTERM 0.8 s into a fit once killed the process with the signal itself, -15)."""
    # a shell starts a background job with SIGINT ignored, and the command keeps an ignored signal ignored
    if signal.getsignal(sig) is signal.SIG_IGN:
        pytest.skip(f"this test process ignores {signal.Signals(sig).name}, and so would the command it starts")
    out = tmp_path / "o.bvh"
    p = subprocess.Popen([sys.executable, "-m", "mocapskel", "fit", str(medium), "-o", str(out), "--no-cache"],
                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, cwd=tmp_path)
    try:
        t0 = time.monotonic()
        while not _handlers_installed(p.pid):
            assert p.poll() is None and time.monotonic() - t0 < 30, "the handlers were never installed"
            time.sleep(0.001)
        if moment != "first_instruction":
            time.sleep(max(0.0, float(moment[:-1]) - (time.monotonic() - t0)))
        p.send_signal(sig)
        _, err = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            p.kill()
    err = err.decode()
    expected = {signal.SIGTERM: (143, "terminated"), signal.SIGINT: (130, "interrupted")}[sig]
    assert p.returncode == expected[0], err
    assert err.strip().splitlines()[-1] == f"mocapskel: error: {expected[1]} — no output was written", err
    assert "Traceback" not in err
    assert not out.exists()
    assert not [q.name for q in tmp_path.iterdir() if ".part" in q.name]


_FORK_RACE = """
import os, signal
from mocapskel.solvers import parallel
from mocapskel.cli import main
signal.signal(signal.{sig}, main.{handler})
# the signal arrives while the fork runs the parent's at-fork hooks (where logging releases its lock)
os.register_at_fork(after_in_parent=lambda: os.kill(os.getpid(), signal.{sig}))
try:
    pid = parallel._fork()
    if pid == 0:
        os._exit(0)
    print("fork returned", flush=True)
except (main.Terminated, main.Interrupted) as e:
    print(type(e).__name__, flush=True)
"""


@pytest.mark.skipif(not hasattr(os, "register_at_fork"), reason="needs os.register_at_fork")
@pytest.mark.parametrize("sig, handler, raised", [("SIGTERM", "_on_sigterm", "Terminated"),
                                                  ("SIGINT", "_on_sigint", "Interrupted")])
def test_a_signal_during_a_fork_is_raised_after_it_not_printed_and_dropped(sig, handler, raised) -> None:
    """A SIGTERM 1.5 s into a fit once arrived while the refinement forked its workers, as Python ran its
    at-fork hooks: the handler's exception was printed with a traceback ("Exception ignored in") and dropped,
    the fit went on (its exit code and last line still right, from the pending signal). Now the handler defers
    it while forking, and the fork, once done, ends its new child and raises it."""
    r = subprocess.run([sys.executable, "-c", _FORK_RACE.format(sig=sig, handler=handler)], capture_output=True,
                       text=True, timeout=60)
    assert r.stdout.split() == [raised], (r.stdout, r.stderr)
    assert "Traceback" not in r.stderr and "Exception ignored" not in r.stderr, r.stderr
