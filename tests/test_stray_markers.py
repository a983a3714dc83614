"""A marker that rides on nothing of the subject (a sync light, a ball, a loose marker) is left out of the
skeleton and said, instead of hanging on it as a one-marker segment with a joint metres away; a marker
that stands still (a robot's base on its table: the lab's own frame) stays (see
:func:`mocapskel.stages.joints.stray_leaves`)."""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from mocapskel import pipeline
from mocapskel.synth.presets import Recipe, make

REALDATA = Path(__file__).resolve().parents[2] / "shared" / "realdata"
MISSING = f"REAL DATA NOT FOUND at {REALDATA} — the real stray-marker test did NOT run (see shared/realdata/README.md)"


def _with_extra(markers, path: np.ndarray, label: str):
    return replace(markers, points=np.concatenate([markers.points, path[:, None]], axis=1),
                   labels=tuple(markers.labels) + (label,))


def _ball(frames: int, rate: float, seed: int, centre: np.ndarray) -> np.ndarray:
    """A marker thrown about on its own: a smooth random path over a couple of metres."""
    rng = np.random.default_rng(seed)
    t = np.arange(frames) / rate
    path = np.zeros((frames, 3))
    for k in range(3):
        for f, a, ph in zip(rng.uniform(0.2, 1.2, 3), rng.uniform(200, 600, 3), rng.uniform(0, 2 * np.pi, 3)):
            path[:, k] += a * np.sin(2 * np.pi * f * t + ph)
    return path + centre


@pytest.mark.parametrize("seed", [1, 2])
def test_a_marker_on_nothing_is_left_out_and_said(seed: int) -> None:
    take = make(Recipe(kind="chain", counts=(4, 3, 3), frames=900, noise_mm=0.3, seed=seed))
    mk = take.markers
    centre = np.nanmean(mk.points.reshape(-1, 3), axis=0) + np.array([0.0, 0.0, 1500.0])
    stray = _with_extra(mk, _ball(mk.n_frames, mk.rate, seed, centre), "SYNC")
    alone = pipeline.fit(mk)
    got = pipeline.fit(stray)
    rep = got.report
    assert [s["markers"] for s in rep["segments"]] == [s["markers"] for s in alone.report["segments"]]
    assert rep["segments_left_out"] == ["SYNC"]
    said = [w for w in rep["warnings"] if w.startswith("marker SYNC left out of the skeleton")]
    assert len(said) == 1, rep["warnings"]
    assert not [c for c in rep["checks"] if c["check"] in ("joint_far", "bone_length")]


def test_a_marker_that_stands_still_stays() -> None:
    """A marker fixed in the lab is a body too (a robot's base): it keeps its segment."""
    take = make(Recipe(kind="chain", counts=(4, 3, 3), frames=900, noise_mm=0.3, seed=1))
    mk = take.markers
    still = np.nanmean(mk.points.reshape(-1, 3), axis=0) + np.array([0.0, 0.0, 1500.0])
    got = pipeline.fit(_with_extra(mk, np.repeat(still[None], mk.n_frames, axis=0), "BASE"))
    assert "BASE" not in got.report["segments_left_out"]
    assert ["BASE"] in [s["markers"] for s in got.report["segments"]]


def test_real_sync_marker_is_left_out() -> None:
    """A wheelchair sprint's sync marker moves by metres on its own; it hung on the forearm with a 2.4 m bone."""
    src = REALDATA / "kineticstoolkit" / "sprintbasket.c3d"
    if not src.is_file():
        pytest.skip(MISSING)
    rep = pipeline.fit(src).report
    assert "Sync:Sync" in rep["segments_left_out"]
    assert "Sync:Sync" not in [m for s in rep["segments"] for m in s["markers"]]
    assert any(w.startswith("marker Sync:Sync left out of the skeleton") for w in rep["warnings"])
    assert not [c for c in rep["checks"] if c["check"] in ("joint_far", "bone_length")]
