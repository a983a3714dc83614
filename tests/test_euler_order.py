"""The BVH rotation order is chosen so that no joint comes near gimbal lock (no Euler spikes)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mocapskel import pipeline
from mocapskel.solvers.bvh_pose import BvhSkeleton, choose_rotation_order, gimbal_margin
from mocapskel.io.bvh_read import read_bvh
from mocapskel.io.bvh import write_bvh
from mocapskel.solvers.rotations import ORDERS, euler_to_matrix, matrix_to_euler, rotvec_to_matrix

SAMPLE = Path(__file__).resolve().parents[1] / "sample_data"


def _spikes(path: Path) -> tuple[int, str]:
    """Joint-frames whose rotation channels step > 10 deg while the rotation turns < 2 deg, and the orders."""
    skel, _, local, _ = read_bvh(path)
    text = path.read_text().splitlines()
    k = next(i for i, l in enumerate(text) if l.startswith("Frame Time"))
    vals = np.loadtxt(text[k + 1 :], ndmin=2)
    cols, c, orders = [], 0, set()
    for l in text[:k]:
        t = l.split()
        if t[:1] == ["CHANNELS"]:
            cols.append([c + i for i, n in enumerate(t[2:]) if n.endswith("rotation")])
            orders.add("".join(n[0] for n in t[2:] if n.endswith("rotation")))
            c += len(t) - 2
    ang = np.stack([vals[:, r] for r in cols], axis=1)
    step = np.abs(np.diff(ang, axis=0)).max(-1)
    true = np.degrees(np.arccos(np.clip((np.einsum("fsij,fsij->fs", local[1:], local[:-1]) - 1) / 2, -1, 1)))
    return int(((step > 10) & (true < 2)).sum()), ",".join(sorted(orders))


def test_gimbal_margin_matches_the_euler_decomposition() -> None:
    rng = np.random.default_rng(0)
    R = rotvec_to_matrix(rng.normal(size=(500, 4, 3)))
    g = gimbal_margin(R)
    for n, order in enumerate(ORDERS):
        b = np.abs(matrix_to_euler(R, order)[..., 1]).max(axis=0)
        np.testing.assert_allclose(g[:, n], 90.0 - b, atol=1e-9)


def _sweep_through_zxy_lock(F: int = 400) -> np.ndarray:
    """(F, 2, 3, 3): joint 1 near ZXY's lock (X = 89.8 deg) as Rz(p) Rx(89.8) Ry(-p): p sweeps 60 deg in
    4 frames, which turns the joint by under 0.1 deg per frame (at the lock Rz(p) Rx(90) Ry(-p) does not
    depend on p) but moves its ZXY channels by 15 deg per frame; slow turns elsewhere."""
    f = np.arange(F)
    p = 60.0 * np.clip((f - 100) / 4.0, 0.0, 1.0)
    slow = 10.0 * np.sin(2 * np.pi * f / F)
    R = np.empty((F, 2, 3, 3))
    R[:, 0] = euler_to_matrix(np.stack([slow, 0 * f, 0 * f], axis=1), "YXZ")
    R[:, 1] = euler_to_matrix(np.stack([p, np.full(F, 89.8), -p], axis=1), "ZXY")
    return R


def test_near_lock_in_zxy_another_order_is_chosen() -> None:
    R = _sweep_through_zxy_lock()
    order = choose_rotation_order(R)
    assert order != "ZXY"
    assert gimbal_margin(R)[:, ORDERS.index(order)].min() > 30.0
    # far from lock the preferred order stays
    far = R.copy()
    far[:, 1] = rotvec_to_matrix(np.radians(np.linspace([0, 0, 0], [40, 30, 50], R.shape[0])))
    assert choose_rotation_order(far) == "ZXY"


def test_written_file_has_no_spike_where_forced_zxy_has(tmp_path: Path) -> None:
    """The check can fail: the same motion written in ZXY spikes; in the chosen order it does not."""
    R = _sweep_through_zxy_lock()
    F = R.shape[0]
    root = np.zeros((F, 3))
    for order, expect in (("ZXY", True), (choose_rotation_order(R), False)):
        skel = BvhSkeleton(("a", "b"), np.array([-1, 0]), np.array([[0, 0, 0], [0, 10.0, 0]]), np.array([[0, 0, 0], [0, 10.0, 0]]), order)
        p = tmp_path / f"{order}.bvh"
        write_bvh(p, skel, root, R, 1 / 120)
        n, orders = _spikes(p)
        assert orders == order
        assert (n > 0) == expect, (order, n)


@pytest.mark.parametrize("up", ["y", "z"])
def test_default_up_y_bvh_of_the_sample_rom_take_has_no_gimbal_spike(tmp_path: Path, up: str) -> None:
    """The generated ROM take's --up y BVH had Euler steps of 16-50 deg where the rotation turned < 2 deg (RTHI)."""
    res = pipeline.fit(SAMPLE / "human_rom.c3d", pipeline.make_params(up=up))
    b = res.bvh
    p = tmp_path / "rom.bvh"
    write_bvh(p, b.skeleton, b.root_pos, b.local_rot, b.frame_time)
    n, _ = _spikes(p)
    assert n == 0
