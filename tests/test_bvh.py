"""Tests of the BVH writer and reader, checked against bvhio (an independent parser)."""
from __future__ import annotations

import re
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from mocapskel.errors import InputError
from mocapskel.io import bvh as bvh_module
from mocapskel.solvers import bvh_pose
from mocapskel.model.tree import NAME_PATTERN, check_names, depth_first_order, sanitize_names
from mocapskel.solvers.bvh_pose import UNIT_SCALE, BvhSkeleton, bvh_rot_to_lab, bvh_to_lab, forward_kinematics, global_to_local_rot, lab_rot_to_bvh, lab_to_bvh, local_to_global_rot
from mocapskel.io.bvh import bvh_text, write_bvh
from mocapskel.io.bvh_read import parse_bvh, read_bvh
from mocapskel.solvers.rotations import ORDERS, euler_to_matrix, rotvec_to_matrix

with warnings.catch_warnings():
    # PyGLM (bvhio's vector library) announces a future rename when imported.
    warnings.filterwarnings("ignore", message="Importing PyGLM", category=PendingDeprecationWarning)
    import bvhio


# --------------------------------------------------------------------------- helpers


def _random_skeleton(rng: np.random.Generator, S: int, order: str = "ZXY") -> BvhSkeleton:
    """A random tree (parents before children, not in depth-first order in general)."""
    parent = np.array([-1] + [int(rng.integers(0, s)) for s in range(1, S)])
    names = [f"J{s:02d}_{rng.integers(100, 999)}" for s in range(S)]
    offset = rng.uniform(-20, 20, (S, 3))
    end_site = np.where(rng.random((S, 1)) < 0.5, 0.0, rng.uniform(-10, 10, (S, 3)))
    return BvhSkeleton(tuple(names), parent, offset, end_site, order)


def _random_motion(rng: np.random.Generator, F: int, S: int, smooth: bool = True) -> tuple[np.ndarray, np.ndarray]:
    t = np.linspace(0, 1, F)[:, None, None]
    if smooth:  # large smooth rotations: several full turns, passes near gimbal lock
        freq, phase = rng.uniform(0.3, 2, (1, S, 3)), rng.uniform(0, 6, (1, S, 3))
        rv = rng.normal(0, 2, (1, S, 3)) * np.sin(2 * np.pi * freq * t + phase)
    else:
        rv = rng.normal(0, 2, (F, S, 3))
    root_pos = np.cumsum(rng.normal(0, 2, (F, 3)), axis=0) + rng.uniform(-30, 30, 3)
    return root_pos, rotvec_to_matrix(rv)


def _bvhio_world_positions(path: Path, frames: list[int]) -> dict[str, np.ndarray]:
    """Joint name -> (len(frames), 3) world positions as bvhio computes them."""
    root = bvhio.readAsHierarchy(str(path))
    out: dict[str, list] = {}
    for f in frames:
        root.loadPose(f)
        for joint, _, _ in root.layout():
            out.setdefault(joint.Name, []).append(list(joint.PositionWorld))
    return {k: np.array(v) for k, v in out.items()}


def _parse_layout(text: str) -> dict:
    """A minimal independent reading of the structure of a BVH text (for the DESIGN rules)."""
    lines = [l.strip() for l in text.splitlines()]
    k = lines.index("MOTION")
    head = lines[:k]
    return {
        "roots": [l.split()[1] for l in head if l.startswith("ROOT ")],
        "names": [l.split()[1] for l in head if l.split()[0] in ("ROOT", "JOINT")],
        "channels": [l.split()[1:] for l in head if l.startswith("CHANNELS")],
        "end_sites": [
            np.array(head[i + 2].split()[1:], dtype=float) for i, l in enumerate(head) if l == "End Site"
        ],
        "frames": lines[k + 1],
        "frame_time": lines[k + 2],
        "motion": [l for l in lines[k + 3 :] if l],
    }


def _fk_by_name(skel: BvhSkeleton, root_pos: np.ndarray, local_rot: np.ndarray) -> dict[str, np.ndarray]:
    P = forward_kinematics(skel, root_pos, local_rot)
    return {n: P[:, s] for s, n in enumerate(skel.names)}


# --------------------------------------------------------------------------- against bvhio


@pytest.mark.parametrize("order", ORDERS)
@pytest.mark.parametrize("seed", [0, 1])
def test_bvhio_world_positions_match_forward_kinematics(tmp_path: Path, order: str, seed: int) -> None:
    rng = np.random.default_rng(100 + seed)
    S, F = int(rng.integers(2, 14)), 40
    skel = _random_skeleton(rng, S, order)
    root_pos, local_rot = _random_motion(rng, F, S, smooth=bool(seed % 2 == 0))
    path = tmp_path / "take.bvh"
    write_bvh(path, skel, root_pos, local_rot, 1 / 120)
    frames = [0, 1, F // 2, F - 1]
    theirs = _bvhio_world_positions(path, frames)
    ours = _fk_by_name(skel, root_pos, local_rot)
    assert set(theirs) == set(ours)
    for name, pos in theirs.items():  # bvhio computes in float32
        np.testing.assert_allclose(pos, ours[name][frames], atol=1e-4, err_msg=name)


def test_euler_convention_is_bvhios() -> None:
    """BVH channels Z X Y mean R = Rz(a) @ Rx(b) @ Ry(c): bvhio's own conversion agrees."""
    from SpatialTransform import Euler

    rng = np.random.default_rng(3)
    for order in ORDERS:
        for ang in rng.uniform(-180, 180, (10, 3)):
            deg = dict(zip(order, ang))
            q = Euler.toQuatFrom(np.radians([deg["X"], deg["Y"], deg["Z"]]).tolist(), order=order, extrinsic=False)
            w, x, y, z = q.w, q.x, q.y, q.z
            theirs = Rotation.from_quat([x, y, z, w]).as_matrix()
            np.testing.assert_allclose(euler_to_matrix(ang, order), theirs, atol=1e-6)


def test_single_joint_and_chain_known_pose(tmp_path: Path) -> None:
    skel = BvhSkeleton(("Root", "Arm", "Hand"), [-1, 0, 1], [[0, 0, 0], [0, 10, 0], [0, 5, 0]], np.zeros((3, 3)))
    local = np.broadcast_to(np.eye(3), (1, 3, 3, 3)).copy()
    local[0, 0] = euler_to_matrix([90, 0, 0], "ZXY")  # root turns +90 about z
    local[0, 1] = euler_to_matrix([0, 90, 0], "ZXY")  # arm turns +90 about (its) x
    P, G = forward_kinematics(skel, np.array([[1.0, 2.0, 3.0]]), local, with_rot=True)
    np.testing.assert_allclose(P[0], [[1, 2, 3], [-9, 2, 3], [-9, 2, 8]], atol=1e-12)
    np.testing.assert_allclose(G[0, 2], local[0, 0] @ local[0, 1], atol=1e-15)
    path = tmp_path / "chain.bvh"
    write_bvh(path, skel, np.array([[1.0, 2.0, 3.0]]), local, 0.01)
    theirs = _bvhio_world_positions(path, [0])
    for s, name in enumerate(skel.names):
        np.testing.assert_allclose(theirs[name][0], P[0, s], atol=1e-5)


HANDWRITTEN = """\
HIERARCHY
ROOT Hips
{
  OFFSET 1.0 2.0 3.0
  CHANNELS 3 Yrotation Xrotation Zrotation
  JOINT Chest
  {
    OFFSET 0 10 0
    CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation
    JOINT Head
    {
      OFFSET 0 8 1
      CHANNELS 3 Xrotation Zrotation Yrotation
      End Site
      {
        OFFSET 0 4 0
      }
    }
  }
  JOINT Leg
  {
    OFFSET 3 -2 0
    CHANNELS 2 Xrotation Zrotation
    End Site
    {
      OFFSET 0 -9 0
    }
  }
}
MOTION
Frames: 3
Frame Time: 0.0333333
10 20 30  0.5 0 10 20 -5 40  -50 60 17  -30 30
-10 5 35  0.5 0 10 40 -25 10  -50 60 17  170 -30
0 0 -90   0.5 0 10 95 90 120  89.999 60 -100  -60 -120
"""


def test_reader_handles_mixed_orders_and_channel_counts_like_bvhio(tmp_path: Path) -> None:
    path = tmp_path / "hand.bvh"
    path.write_text(HANDWRITTEN)
    skel, root_pos, local_rot, ft = read_bvh(path)
    assert skel.names == ("Hips", "Chest", "Head", "Leg") and list(skel.parent) == [-1, 0, 1, 0]
    assert skel.order == "YXZ"  # the first joint with three rotation channels: the root
    np.testing.assert_allclose(root_pos, np.broadcast_to([1.0, 2.0, 3.0], (3, 3)))
    np.testing.assert_allclose(skel.offset[1], [0.5, 0, 10])  # constant position channels replace the OFFSET
    np.testing.assert_allclose(skel.end_site[[2, 3]], [[0, 4, 0], [0, -9, 0]])
    assert ft == pytest.approx(0.0333333)
    np.testing.assert_allclose(local_rot[0, 0], euler_to_matrix([10, 20, 30], "YXZ"), atol=1e-15)
    np.testing.assert_allclose(local_rot[0, 3], euler_to_matrix([-30, 30, 0], "XZY"), atol=1e-15)
    theirs = _bvhio_world_positions(path, [0, 1, 2])
    ours = _fk_by_name(skel, root_pos, local_rot)
    for name, pos in theirs.items():
        np.testing.assert_allclose(pos, ours[name], atol=1e-4, err_msg=name)


# --------------------------------------------------------------------------- own round trip


@pytest.mark.parametrize("order", ["ZXY", "XYZ", "YZX"])
def test_write_read_round_trip(tmp_path: Path, order: str) -> None:
    rng = np.random.default_rng(7)
    S, F = 11, 60
    skel = _random_skeleton(rng, S, order)
    root_pos, local_rot = _random_motion(rng, F, S)
    path = tmp_path / "rt.bvh"
    write_bvh(path, skel, root_pos, local_rot, 1 / 240, precision=8)
    back, rp, lr, ft = read_bvh(path)
    dfs = depth_first_order(skel.parent)
    assert back.names == tuple(skel.names[s] for s in dfs)
    inv = np.argsort(dfs)
    np.testing.assert_array_equal(back.parent, np.where(skel.parent[dfs] < 0, -1, inv[skel.parent[dfs]]))
    np.testing.assert_allclose(back.offset, skel.offset[dfs], atol=1e-8)
    assert back.order == order
    np.testing.assert_allclose(rp, root_pos, atol=1e-8)
    np.testing.assert_allclose(lr, local_rot[:, dfs], atol=1e-9)
    assert ft == pytest.approx(1 / 240, rel=1e-6)
    np.testing.assert_allclose(forward_kinematics(back, rp, lr), forward_kinematics(skel, root_pos, local_rot)[:, dfs],
                               atol=1e-6)
    # a depth-first skeleton round-trips onto itself, and writes the same text again
    assert np.array_equal(depth_first_order(back.parent), np.arange(S))
    text1 = path.read_text()
    write_bvh(tmp_path / "again.bvh", back, rp, lr, ft, precision=8)
    back2, rp2, lr2, _ = read_bvh(tmp_path / "again.bvh")
    assert back2.names == back.names
    np.testing.assert_allclose(lr2, lr, atol=1e-9)
    assert text1.splitlines()[: 5 * S] == (tmp_path / "again.bvh").read_text().splitlines()[: 5 * S]


def test_written_angles_are_continuous(tmp_path: Path) -> None:
    # a joint spinning four full turns about y with a wobble: the channel keeps counting
    F = 200
    t = np.linspace(0, 1, F)
    skel = BvhSkeleton(("Root", "Spin"), [-1, 0], [[0, 0, 0], [0, 10, 0]], np.zeros((2, 3)))
    local = np.empty((F, 2, 3, 3))
    local[:, 0] = euler_to_matrix(np.stack([10 * np.sin(6 * t), 5 * t, 1440 * t], axis=1), "ZXY")
    local[:, 1] = euler_to_matrix(np.stack([170 + 40 * t, 85 + 20 * np.sin(3 * t), -100 * t], axis=1), "ZXY")
    layout = _parse_layout(bvh_text(skel, np.zeros((F, 3)), local, 0.01))
    values = np.array([l.split() for l in layout["motion"]], dtype=float)
    assert np.abs(np.diff(values[:, 3:], axis=0)).max() < 12
    assert values[-1, 5] == pytest.approx(1440, abs=1e-6)


def test_zero_frames(tmp_path: Path) -> None:
    skel = BvhSkeleton(("Only",), [-1], np.zeros((1, 3)), np.zeros((1, 3)))
    write_bvh(tmp_path / "z.bvh", skel, np.zeros((0, 3)), np.zeros((0, 1, 3, 3)), 0.01)
    back, rp, lr, ft = read_bvh(tmp_path / "z.bvh")
    assert back.names == ("Only",) and rp.shape == (0, 3) and lr.shape == (0, 1, 3, 3) and ft == 0.01


@settings(max_examples=200, deadline=None)
@given(
    st.integers(1, 10),
    st.lists(st.floats(-1e7, 1e7, allow_subnormal=True), min_size=1, max_size=40),
    st.integers(1, 5),
)
def test_motion_numbers_are_exactly_printf(precision: int, values: list[float], columns: int) -> None:
    """The vectorised formatter writes what '%.{p}f' would, byte for byte."""
    rng = np.random.default_rng(len(values))
    extra = [0.5 * 10.0**-precision, -0.5 * 10.0**-precision, -1e-12, 1e15, -3e17, 123.456789]
    flat = np.array(values + extra + list(rng.normal(0, 10.0 ** rng.integers(-3, 6), 24)))
    blk = np.round(flat[: len(flat) // columns * columns].reshape(-1, columns), precision) + 0.0
    row = " ".join([f"%.{precision}f"] * columns) + "\n"
    assert bvh_module._format_fixed(blk, precision) == ((row * blk.shape[0]) % tuple(blk.ravel().tolist())).encode()
    small = blk[np.abs(blk).max(axis=1) < 1e6]  # the numpy path (not the '%' fallback)
    if small.size:
        assert bvh_module._format_fixed(small, precision) == ((row * small.shape[0]) % tuple(small.ravel().tolist())).encode()


# --------------------------------------------------------------------------- DESIGN rules


@pytest.mark.parametrize("seed", range(4))
def test_design_rules_hold_in_the_text(seed: int) -> None:
    rng = np.random.default_rng(200 + seed)
    S, F = int(rng.integers(1, 16)), int(rng.integers(1, 30))
    order = ORDERS[seed]
    skel = _random_skeleton(rng, S, order)
    if seed == 0:  # leaves without any End Site given
        skel = BvhSkeleton(skel.names, skel.parent, skel.offset, np.zeros((S, 3)), order)
    root_pos, local_rot = _random_motion(rng, F, S)
    rate = [120.0, 100.0, 29.97, 1000.0][seed]
    layout = _parse_layout(bvh_text(skel, root_pos, local_rot, 1 / rate))
    rot = [f"{c}rotation" for c in order]

    assert layout["roots"] == [skel.names[0]]
    assert layout["channels"][0] == ["6", "Xposition", "Yposition", "Zposition", *rot]
    assert all(c == ["3", *rot] for c in layout["channels"][1:]) and len(layout["channels"]) == S
    assert layout["frames"] == f"Frames: {F}"
    m = re.fullmatch(r"Frame Time: (\d+\.\d{8,})", layout["frame_time"])
    assert m and 1 / float(m.group(1)) == pytest.approx(rate, rel=1e-9)
    assert len(layout["motion"]) == F and all(len(l.split()) == 3 + 3 * S for l in layout["motion"])
    n_leaves = S - len(set(skel.parent[1:].tolist()))
    assert len(layout["end_sites"]) == n_leaves
    assert all(np.abs(e).max() > 0 for e in layout["end_sites"])
    names = layout["names"]
    assert sorted(names) == sorted(skel.names)
    assert all(NAME_PATTERN.match(n) for n in names) and len(set(names)) == S
    assert not any(a != b and b.startswith(a) for a in names for b in names)


def test_zero_end_site_gets_a_default_along_the_bone() -> None:
    skel = BvhSkeleton(("Root", "Arm", "Hand", "Nub"), [-1, 0, 1, 0],
                       [[0, 0, 0], [0, 10, 0], [4, 0, 0], [0, 0, 0]], [[0, 0, 0], [0, 0, 0], [0, 0, 0], [0, 0, 1e-9]])
    layout = _parse_layout(bvh_text(skel, np.zeros((1, 3)), np.broadcast_to(np.eye(3), (1, 4, 3, 3)), 0.01))
    hand, nub = layout["end_sites"]
    np.testing.assert_allclose(hand, [2, 0, 0])  # half the leaf's own bone, further along it
    np.testing.assert_allclose(nub, [0, 0.25 * np.median([10, 4]), 0])  # zero-length leaf bone: +Y


# --------------------------------------------------------------------------- names


def test_sanitize_names_examples() -> None:
    got = sanitize_names(["Left Hip", "1st", "", "Hip", "Hips", "A", "A", "ü", "J1", "J10", "x-y", "A_"])
    check_names(got)
    assert got[0] == "Left_Hip" and got[1] == "_1st" and got[2] == "joint" and got[4] == "Hips"
    assert got[3].startswith("Hip_") and got[7].startswith("_") and got[10] == "x_y" and got[9] == "J10"
    assert sanitize_names(["Hips", "Spine", "Head"]) == ["Hips", "Spine", "Head"]  # valid names are kept
    dup = sanitize_names(["A"] * 12)
    check_names(dup)
    assert dup[0] == "A_01" and dup[-1] == "A_12"


@settings(max_examples=300, deadline=None)
@given(st.lists(st.text(max_size=6), max_size=14))
def test_sanitize_names_makes_any_list_valid(names: list[str]) -> None:
    out = sanitize_names(names)
    assert len(out) == len(names)
    check_names(out)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.text(alphabet="aA_1", min_size=1, max_size=4), max_size=40))
def test_sanitize_names_survives_many_prefix_clashes(names: list[str]) -> None:
    check_names(sanitize_names(names))


@pytest.mark.parametrize(
    ("names", "why"),
    [(("Hips", "Hip"), "prefix"), (("A", "A"), "duplicate"), (("A", "b c"), "invalid"), (("A", "2B"), "invalid")],
)
def test_writer_refuses_bad_names(tmp_path: Path, names: tuple[str, ...], why: str) -> None:
    skel = BvhSkeleton(names, [-1, 0], [[0, 0, 0], [0, 1, 0]], np.zeros((2, 3)))
    with pytest.raises(ValueError, match=why):
        write_bvh(tmp_path / "x.bvh", skel, np.zeros((1, 3)), np.broadcast_to(np.eye(3), (1, 2, 3, 3)), 0.01)
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------- refusals, atomicity


def _small() -> tuple[BvhSkeleton, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(11)
    skel = _random_skeleton(rng, 5)
    root_pos, local_rot = _random_motion(rng, 20, 5)
    return skel, root_pos, local_rot


@pytest.mark.parametrize("where", ["root_pos", "local_rot"])
def test_nan_is_refused_and_nothing_is_written(tmp_path: Path, where: str) -> None:
    skel, root_pos, local_rot = _small()
    (root_pos if where == "root_pos" else local_rot)[7, ...] = np.nan
    target = tmp_path / "out.bvh"
    with pytest.raises(ValueError, match="NaN"):
        write_bvh(target, skel, root_pos, local_rot, 0.01)
    assert list(tmp_path.iterdir()) == []
    target.write_text("old")
    with pytest.raises(ValueError, match="NaN"):
        write_bvh(target, skel, root_pos, local_rot, 0.01)
    assert target.read_text() == "old" and list(tmp_path.iterdir()) == [target]


def test_failure_mid_write_leaves_no_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    skel, root_pos, local_rot = _small()

    def failing_blocks(motion: np.ndarray, precision: int):
        yield b"1 2 3\n"
        raise KeyboardInterrupt

    monkeypatch.setattr(bvh_module, "_motion_blocks", failing_blocks)
    target = tmp_path / "out.bvh"
    with pytest.raises(KeyboardInterrupt):
        write_bvh(target, skel, root_pos, local_rot, 0.01)
    assert list(tmp_path.iterdir()) == []


def test_writer_refuses_bad_input(tmp_path: Path) -> None:
    skel, root_pos, local_rot = _small()
    with pytest.raises(ValueError, match="rotation"):
        write_bvh(tmp_path / "a.bvh", skel, root_pos, 2 * local_rot, 0.01)
    with pytest.raises(ValueError, match="rotation"):  # a reflection
        write_bvh(tmp_path / "a.bvh", skel, root_pos, -local_rot, 0.01)
    with pytest.raises(ValueError, match="local_rot"):
        write_bvh(tmp_path / "a.bvh", skel, root_pos, local_rot[:, :3], 0.01)
    with pytest.raises(ValueError, match="frame_time"):
        write_bvh(tmp_path / "a.bvh", skel, root_pos, local_rot, 0.0)
    with pytest.raises(ValueError, match="parent"):
        BvhSkeleton(("A", "B"), [-1, 1], np.zeros((2, 3)), np.zeros((2, 3)))
    with pytest.raises(ValueError, match="same S joints"):
        BvhSkeleton(("A", "B"), [-1, 0], np.zeros((3, 3)), np.zeros((2, 3)))
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------- malformed files


def _good_text() -> str:
    skel, root_pos, local_rot = _small()
    return bvh_text(skel, root_pos[:3], local_rot[:3], 0.01)


@pytest.mark.parametrize(
    ("mutate", "match"),
    [
        (lambda t: "", "no MOTION"),
        (lambda t: t.replace("HIERARCHY", "HIERARCHIE"), "HIERARCHY"),
        (lambda t: t.split("MOTION")[0], "no MOTION"),
        (lambda t: t.replace("OFFSET", "OFFSET x", 1), r"line 4: OFFSET needs 3 numbers"),
        (lambda t: t.replace("CHANNELS 3", "CHANNELS 3 Wrotation", 1), "unknown channel 'Wrotation'"),
        (lambda t: t.replace("CHANNELS 6", "CHANNELS seven", 1), "channel count"),
        (lambda t: t.replace("End Site", "End Sight", 1), "End Sight"),
        (lambda t: t.replace("}\nMOTION", "MOTION"), "file ends"),
        (lambda t: t.replace("}\nMOTION", "}\n}\nMOTION"), "after the ROOT"),
        (lambda t: t.replace("MOTION", "ROOT Two\n{\nOFFSET 0 0 0\n}\nMOTION"), "second ROOT"),
        (lambda t: t.replace("Frames: 3", "Frames: 4"), "says 4 but the file has 3"),
        (lambda t: t.replace("Frames: 3", "Frames 3"), "Frames: <count>"),
        (lambda t: re.sub(r"Frame Time: \S+", "Frame Time: -1", t), "Frame Time"),
        (lambda t: t.rstrip("\n") + " 1.5\n", r"values where the CHANNELS declare"),
        (lambda t: re.sub(r"\S+\s*$", "abc\n", t), "line 44: a motion value is not a number"),
        (lambda t: re.sub(r"\S+\s*$", "nan\n", t), "line 44: a motion value is not finite"),
    ],
)
def test_malformed_files_raise_input_error(tmp_path: Path, mutate, match: str) -> None:
    path = tmp_path / "bad.bvh"
    path.write_text(mutate(_good_text()))
    with pytest.raises(InputError, match=match) as err:
        read_bvh(path)
    assert str(path) in str(err.value)


def test_missing_file_and_moving_child_joint(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="cannot read"):
        read_bvh(tmp_path / "nope.bvh")
    moving = HANDWRITTEN.replace("0.5 0 10 40", "0.7 0 10 40")
    with pytest.raises(InputError, match="'Chest' has translation channels that change"):
        parse_bvh(moving, "moving.bvh")


# --------------------------------------------------------------------------- kinematics, coordinates


def test_global_and_local_rotations_round_trip() -> None:
    rng = np.random.default_rng(12)
    skel = _random_skeleton(rng, 9)
    root_pos, local = _random_motion(rng, 10, 9)
    _, G = forward_kinematics(skel, root_pos, local, with_rot=True)
    np.testing.assert_allclose(local_to_global_rot(skel.parent, local), G, atol=1e-13)
    np.testing.assert_allclose(global_to_local_rot(skel.parent, G), local, atol=1e-13)


@pytest.mark.parametrize(("up", "units"), [("y", "cm"), ("z", "mm"), ("y", "m")])
def test_export_recipe_puts_lab_motion_into_bvh(tmp_path: Path, up: str, units: str) -> None:
    """Global lab rotations (rest axes = lab axes) -> BVH, as the module docstring says; bvhio agrees."""
    rng = np.random.default_rng(14)
    S, F = 7, 12
    parent = np.array([-1, 0, 1, 0, 3, 0, 5])
    origin = rng.uniform(-400, 400, (S, 3))  # mm, lab frame, at the rest frame
    rot = Rotation.random(F * S, random_state=rng).as_matrix().reshape(F, S, 3, 3)  # global, relative to rest
    root = rng.uniform(-1000, 1000, (F, 3))
    lab = np.empty((F, S, 3))
    lab[:, 0] = root
    for s in range(1, S):
        lab[:, s] = lab[:, parent[s]] + rot[:, parent[s]] @ (origin[s] - origin[parent[s]])
    off = origin.copy()
    off[1:] -= origin[parent[1:]]
    skel = BvhSkeleton(("Pelvis", "Spine", "Head", "LThigh", "LShin", "RThigh", "RShin"), parent,
                       lab_to_bvh(off, up, units), np.zeros((S, 3)))
    root_b = lab_to_bvh(root, up, units)
    local = global_to_local_rot(parent, lab_rot_to_bvh(rot, up))
    np.testing.assert_allclose(bvh_to_lab(forward_kinematics(skel, root_b, local), up, units), lab, atol=1e-9)
    path = tmp_path / "lab.bvh"
    write_bvh(path, skel, root_b, local, 1 / 100, precision=8 if units == "m" else 6)
    theirs = _bvhio_world_positions(path, [0, F - 1])
    # 1e-4 of the output unit, or bvhio's float32 rounding where that is coarser (mm)
    tol = max(1e-4 * UNIT_SCALE[units], 1e-6 * np.abs(lab).max())
    for s, name in enumerate(skel.names):
        np.testing.assert_allclose(bvh_to_lab(theirs[name], up, units), lab[[0, F - 1], s], atol=tol)


def test_lab_to_bvh_axes_and_units() -> None:
    p = np.array([[10.0, 20.0, 30.0], [np.nan, 1.0, 2.0]])
    np.testing.assert_allclose(lab_to_bvh(p, "z", "mm"), p)
    np.testing.assert_allclose(lab_to_bvh(p[0], "y", "mm"), [10, 30, -20])
    np.testing.assert_allclose(lab_to_bvh(p[0], "y", "cm"), [1, 3, -2])
    np.testing.assert_allclose(lab_to_bvh(p[0], "z", "m"), [0.01, 0.02, 0.03])
    assert np.isnan(lab_to_bvh(p, "y", "cm")[1]).sum() == 1
    assert UNIT_SCALE == {"mm": 1.0, "cm": 10.0, "m": 1000.0}
    C = lab_to_bvh(np.eye(3), "y", "mm").T  # columns: images of the lab axes
    assert np.linalg.det(C) == pytest.approx(1.0)
    rng = np.random.default_rng(13)
    pts = rng.normal(size=(4, 5, 3))
    R = Rotation.random(4, random_state=rng).as_matrix()
    for up in ("y", "z"):
        for units in ("mm", "cm", "m"):
            np.testing.assert_allclose(bvh_to_lab(lab_to_bvh(pts, up, units), up, units), pts, atol=1e-12)
        # rotating in the lab then converting = converting then rotating in BVH
        Rb = lab_rot_to_bvh(R, up)
        np.testing.assert_allclose(lab_to_bvh(np.einsum("fij,fpj->fpi", R, pts), up, "cm"),
                                   np.einsum("fij,fpj->fpi", Rb, lab_to_bvh(pts, up, "cm")), atol=1e-12)
        np.testing.assert_allclose(np.linalg.det(Rb), 1, atol=1e-12)
        np.testing.assert_allclose(bvh_rot_to_lab(Rb, up), R, atol=1e-15)
    with pytest.raises(ValueError, match="up"):
        lab_to_bvh(pts, "x", "cm")
    with pytest.raises(ValueError, match="units"):
        lab_to_bvh(pts, "y", "inch")


# --------------------------------------------------------------------------- the fast writer against the plain one


def _plain_bvh_text(skel: BvhSkeleton, root_pos: np.ndarray, local_rot: np.ndarray, frame_time: float) -> str:
    """The text written the plain way: C-ordered arrays, '%.6f' per number (the writer's reference)."""
    from mocapskel.solvers.rotations import matrix_to_euler, unwrap_euler

    F, S = local_rot.shape[:2]
    dfs = depth_first_order(skel.parent)
    ang = unwrap_euler(matrix_to_euler(np.ascontiguousarray(local_rot), skel.order), skel.order)
    motion = np.round(np.concatenate([root_pos, ang[:, dfs].reshape(F, 3 * S)], axis=1), 6) + 0.0
    header = bvh_module._header(skel, dfs, F, frame_time, 6)
    return header + "".join(" ".join("%.6f" % v for v in row) + "\n" for row in motion.tolist())


@pytest.mark.parametrize("seed", range(3))
def test_fast_writer_is_byte_identical_to_plain_formatting(tmp_path: Path, seed: int) -> None:
    rng = np.random.default_rng(300 + seed)
    S, F = int(rng.integers(2, 18)), int(rng.integers(1, 2500))
    skel = _random_skeleton(rng, S, ORDERS[seed])
    root_pos, local_rot = _random_motion(rng, F, S, smooth=seed != 1)
    root_pos = root_pos * 10.0 ** rng.integers(-3, 4)  # mm to km: 1 to 7 integer digits
    plain = _plain_bvh_text(skel, root_pos, local_rot, 1 / 120)
    path = tmp_path / "fast.bvh"
    write_bvh(path, skel, root_pos, local_rot, 1 / 120)
    assert path.read_bytes() == plain.encode("ascii")
    assert bvh_text(skel, root_pos, local_rot, 1 / 120) == plain
    # and it reads back, by our reader and by bvhio, to the numbers written
    back, rp, lr, _ = read_bvh(path)
    np.testing.assert_allclose(rp, root_pos, atol=5e-7)
    np.testing.assert_allclose(lr, local_rot[:, depth_first_order(skel.parent)], atol=1e-7)
    theirs = _bvhio_world_positions(path, [0, F - 1])
    ours = _fk_by_name(back, rp, lr)
    for name, pos in theirs.items():
        np.testing.assert_allclose(pos, ours[name][[0, F - 1]], atol=1e-3 * max(1.0, np.abs(root_pos).max() * 1e-4), err_msg=name)


def test_writer_output_does_not_depend_on_memory_layout(tmp_path: Path) -> None:
    rng = np.random.default_rng(7)
    S, F = 9, 700
    skel = _random_skeleton(rng, S)
    root_pos, local_rot = _random_motion(rng, F, S)
    want = bvh_text(skel, root_pos, local_rot, 0.01)
    time_major = np.moveaxis(np.ascontiguousarray(np.moveaxis(local_rot, 0, -1)), -1, 0)
    entry_major = np.moveaxis(np.ascontiguousarray(np.moveaxis(local_rot, (2, 3), (0, 1))), (0, 1), (2, 3))
    strided = np.stack([local_rot, local_rot], axis=1)[:, 0]
    for layout in (time_major, entry_major, np.asfortranarray(local_rot), strided):
        np.testing.assert_array_equal(layout, local_rot)
        assert bvh_text(skel, root_pos, layout, 0.01) == want


@pytest.mark.parametrize("columns", [1, 2, 5])
def test_six_decimals_fast_path_edge_values(columns: int) -> None:
    """Precision 6 packs each number in two 64-bit words: integer parts of 0 to 7 digits, signs, carries."""
    vals = [0.0, 1e-6, -1e-6, 0.5e-6, 0.9999995, -0.9999995, 9.9999995, 10.0, 99.999999, 100.0, 999.9999995, 1000.0,
            12345.678901, -12345.678901, 999999.999999, 1000000.0, 9999999.999999, -9999999.999999, 9999999.9999996, 1e7,
            -1e7, 123456789.5, 7.25, -0.000001, 3.1415926535]
    flat = np.array(vals * columns)
    blk = np.round(flat[: len(flat) // columns * columns].reshape(-1, columns), 6) + 0.0
    row = " ".join(["%.6f"] * columns) + "\n"
    want = ((row * blk.shape[0]) % tuple(blk.ravel().tolist())).encode()
    assert bvh_module._format_fixed(blk, 6) == want
    small = blk[np.abs(blk).max(axis=1) < 1e7]  # all through the packed path
    assert bvh_module._format_fixed(small, 6) == ((row * small.shape[0]) % tuple(small.ravel().tolist())).encode()


def test_lab_rot_to_bvh_is_the_signed_permutation_exactly() -> None:
    rng = np.random.default_rng(8)
    R = rotvec_to_matrix(rng.normal(size=(300, 6, 3)))
    joints = np.array([3, 0, 5, 1, 2, 4])
    for up in ("y", "z"):
        C = bvh_pose._axes(up)
        want = C @ R @ C.T
        got = lab_rot_to_bvh(R, up)
        np.testing.assert_array_equal(got, want)
        assert np.moveaxis(got, 0, -1).flags.c_contiguous  # frames innermost
        np.testing.assert_array_equal(lab_rot_to_bvh(R, up, joints=joints), want[:, joints])
        np.testing.assert_array_equal(bvh_rot_to_lab(got, up), R)
        np.testing.assert_array_equal(lab_rot_to_bvh(R[0], up), want[0])  # one stack of matrices
        np.testing.assert_array_equal(lab_rot_to_bvh(R[:0], up), want[:0])


def test_global_to_local_rot_matches_matmul_in_any_layout() -> None:
    rng = np.random.default_rng(9)
    G = rotvec_to_matrix(rng.normal(size=(200, 7, 3)))
    parent = np.array([3, -1, 1, 1, 3, 0, 5])  # any numbering
    want = G.copy()
    has = parent >= 0
    want[:, has] = np.swapaxes(G[:, parent[has]], -1, -2) @ G[:, has]
    for rot in (G, lab_rot_to_bvh(G, "z")):  # C order, frames innermost
        got = global_to_local_rot(parent, rot)
        np.testing.assert_allclose(got, want, rtol=0, atol=4e-16)
        assert got.strides == rot.strides


@pytest.mark.parametrize("rate", [1.0, 23.976, 24.0, 25.0, 29.97, 30.0, 50.0, 59.94, 60.0, 100.0, 120.0, 148.0,
                                  150.0, 200.0, 240.0, 250.0, 300.0, 360.0, 480.0, 500.0, 960.0, 1000.0, 2000.0, 10000.0])
def test_frame_time_reads_back_as_the_rate(tmp_path: Path, rate: float) -> None:
    skel = BvhSkeleton(("A", "B"), np.array([-1, 0]), np.array([[0.0, 0, 0], [0, 1, 0]]), np.zeros((2, 3)))
    path = tmp_path / "r.bvh"
    write_bvh(path, skel, np.zeros((2, 3)), np.broadcast_to(np.eye(3), (2, 2, 3, 3)), 1.0 / rate)
    line = next(l for l in path.read_text().splitlines() if l.startswith("Frame Time:"))
    written = line.split(":", 1)[1].strip()
    assert len(written.split(".")[1]) >= 8
    _, _, _, frame_time = read_bvh(path)
    assert float(written) == frame_time
    # the rate an importer computes as 1 / Frame Time, to 10 significant digits
    assert abs(1.0 / frame_time - rate) <= 5e-10 * rate
    assert round(1.0 / frame_time, 6) == rate


def test_frame_time_of_120_hz_is_written_with_ten_digits() -> None:
    from mocapskel.io.bvh import format_frame_time

    assert format_frame_time(1 / 120) == "0.008333333333"
    assert format_frame_time(0.01) == "0.01000000000"
