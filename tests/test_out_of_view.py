"""A limb out of view on a realistic generated walk (the CMU-style 41-marker set, skin motion driven by
the joint angles): where nothing of it is seen, IK keeps its joints' angles, which puts its markers
nearer where they truly were than holding it still in the lab does, and the report says for how many
frames each segment was out of view and warns when that is a tenth of the take or more."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from mocapskel import evaluate, pipeline
from mocapskel.synth.presets import make, realistic

FOREARM_AND_HAND = ("LELB", "LFRM", "LWRA", "LWRB", "LFIN")
FOOT = ("RHEE", "RTOE", "RMT5")


@pytest.fixture(scope="module")
def hidden_walk():
    take = make(realistic(seed=2, frames=600, motion="walk", markerset="cmu41"))
    labels = list(take.markers.labels)
    hidden = np.zeros(take.markers.points.shape[:2], dtype=bool)
    hidden[:120, [labels.index(m) for m in FOREARM_AND_HAND]] = True  # the first fifth
    hidden[480:, [labels.index(m) for m in FOOT]] = True  # the last fifth
    pts = take.markers.points.copy()
    pts[hidden] = np.nan
    res = pipeline.fit(replace(take.markers, points=pts), pipeline.make_params(up="z", units="mm"))
    return take, hidden, res


def _predicted(motion, rot: np.ndarray) -> np.ndarray:
    """(F, M, 3) every skeleton marker where the poses ``rot`` (F, S, 3, 3) put it (root and joints as solved)."""
    sk = motion.skeleton
    J = evaluate.joint_positions(replace(motion, rot=rot))
    seg = np.maximum(sk.marker_segment, 0)
    return J[:, seg] + np.einsum("fmij,mj->fmi", rot[:, seg], sk.marker_local)


def test_a_limb_out_of_view_keeps_its_joint_angles_nearer_the_truth_than_held_in_the_lab(hidden_walk):
    take, hidden, res = hidden_walk
    mot = res.motion
    sk = mot.skeleton
    cols = [list(take.markers.labels).index(lb) for lb in sk.labels]
    truth = take.markers.points[:, cols]
    hid = hidden[:, cols] & (sk.marker_segment >= 0)
    assert hid.any(axis=0).sum() == len(FOREARM_AND_HAND) + len(FOOT)
    ours = np.linalg.norm(_predicted(mot, mot.rot) - truth, axis=-1)[hid]
    # the other policy, from the same fit: every segment whose markers are all hidden holds, in the lab,
    # its rotation of the nearest frame where one is seen
    lab = mot.rot.copy()
    for s in np.unique(sk.marker_segment[hid.any(axis=0)]):
        mine = sk.marker_segment == s
        gone = ~np.isfinite(res.motion.residual[:, mine]).any(axis=1)
        if gone.all() or not gone.any():
            continue
        idx = np.where(~gone, np.arange(len(gone)), -1)
        np.maximum.accumulate(idx, out=idx)
        nxt = np.where(~gone, np.arange(len(gone)), len(gone))
        nxt = np.minimum.accumulate(nxt[::-1])[::-1]
        near = np.where(idx >= 0, idx, nxt)
        lab[gone, s] = mot.rot[near[gone], s]
    held = np.linalg.norm(_predicted(mot, lab) - truth, axis=-1)[hid]
    rms = lambda e: float(np.sqrt(np.mean(e**2)))  # noqa: E731
    assert rms(ours) < 0.75 * rms(held), (rms(ours), rms(held))
    assert rms(ours) < 80.0, rms(ours)


def test_the_report_counts_the_frames_each_segment_is_out_of_view(hidden_walk):
    take, hidden, res = hidden_walk
    sk = res.motion.skeleton
    out = res.report["ik"]["out_of_view_frames"]
    labels = list(sk.labels)
    for group, frames in ((FOREARM_AND_HAND, 120), (FOOT, 120)):
        segs = {int(sk.marker_segment[labels.index(m)]) for m in group}
        # the limb's own segments, whose every marker was hidden: out of view at least as long as hidden,
        # and longer only by what the clean stage trims at the ends of a gap (a few frames)
        whole = [s for s in segs if set(np.array(labels)[sk.marker_segment == s]) <= set(group)]
        assert whole, (group, segs)
        for s in whole:
            n = out.get(sk.names[s], 0)
            assert frames <= n <= frames + 12, (sk.names[s], n)
    # nothing else of the body goes out of view
    named = {sk.names[s] for g in (FOREARM_AND_HAND, FOOT) for s in {int(sk.marker_segment[labels.index(m)]) for m in g}}
    assert set(out) <= named, out
    # out of view in a fifth of the take (more than a tenth): each is said, with its frames
    said = [w for w in res.report["warnings"] if "is out of view in" in w]
    assert len(said) == len(out), said
    for name, n in out.items():
        (w,) = [w for w in said if w.startswith(f"segment {name} (")]
        assert f"out of view in {n} of 600 frames" in w and "made up" in w, w
    assert any("frames 0-" in w for w in said) and any("-599)" in w for w in said), said


def test_frames_where_nothing_is_seen_are_not_counted_out_of_view(hidden_walk):
    from mocapskel.artifacts import markers_of
    from mocapskel.solvers.ik.motion import solve

    _, _, res = hidden_walk
    sk = res.motion.skeleton
    pts = markers_of(sk).points.copy()
    before = solve(sk, pts, rate=120.0).info["out_of_view_frames"]
    pts[300:310] = np.nan  # nothing seen: the whole body held, no limb more than another
    after = solve(sk, pts, rate=120.0).info["out_of_view_frames"]
    assert before and after == before, (before, after)
