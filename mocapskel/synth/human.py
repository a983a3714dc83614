"""A seeded synthetic human: 15 rigid segments, 48 skin markers, exact truth.

Lab frame
---------
Right-handed, **Z up**, millimetres. In the rest pose (standing, arms hanging
at the sides, palms forward) the subject faces **+X** and **+Y** is the
subject's **left**. The floor is the plane ``z = 0``. Every segment's rest
orientation is the lab axes (the convention of :mod:`mocapskel.artifacts`), so
a joint rotation is a rotation of the child relative to the parent, expressed
in lab axes at rest.

Body
----
Segments (parent first)::

    0 Pelvis (root)  1 Torso  2 Head
    3 LUpperArm  4 LForearm  5 LHand     6 RUpperArm  7 RForearm  8 RHand
    9 LThigh    10 LShank   11 LFoot    12 RThigh    13 RShank   14 RFoot

14 joints, one per non-root segment (named in ``truth.info["joint_names"]``):
Lumbar, Neck, L/RShoulder, L/RWrist, L/RHip, L/RAnkle are ball joints (3 DoF);
L/RElbow and L/RKnee are hinges: one large rotation about an anatomical axis
plus a little varus/valgus and axial rotation (±5° and ±12° by default, the
``hinge_slack_deg`` of :func:`human_take`), so that the joint centre along the
hinge axis stays observable, as on a real knee.

Adult proportions for a ~1.75 m subject (hip joints 925 mm above the floor,
thigh 430, shank 420, upper arm 300, forearm 255 mm, lumbar joint to C7
~470 mm); each body part varies by up to ±3 % between subjects, and ``scale``
multiplies everything.

Markers sit on the skin around each segment, 25–85 mm from a limb's bone
axis (85–135 mm around the torso and pelvis, ~95 mm around the head), spread
along it, at least ~45 mm from any joint; the first three of a segment always
make a well-shaped triangle (never nearly collinear). The default is 48 markers: pelvis, torso and
head 4 each, every limb segment 3. Labels are ``<code><k>`` with codes
``PELV TRSO HEAD LUPA LFRM LHND RUPA RFRM RHND LTHI LSHN LFOT RTHI RSHN RFOT``
(e.g. ``LTHI1``). The first ``n`` markers of a segment do not depend on how
many are asked for, so a 2-marker subject is a subset of the 3-marker one.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from ..artifacts import Markers
from .body import (
    _S,
    HINGES,
    JOINT_NAMES,
    PARENT,
    SEGMENTS,
    _check_take_args,
    _hinge_frame,
    _make_subject,
    _marker_counts,
)
from .forward import _floor_lift, _forward
from .motions import _rom_motion, _walk_motion
from .soft_tissue import _SOFT_TISSUE_BAND_HZ, _soft_tissue
from .truth import SynthTake, Truth

__all__ = ["MOTIONS", "human_take"]

MOTIONS: tuple[str, ...] = ("rom", "walk")


# --------------------------------------------------------------------------- public


def human_take(
    *,
    rng: np.random.Generator,
    n_frames: int = 7200,
    rate: float = 120.0,
    markers_per_segment: int | Sequence[int] | Mapping[str, int] | None = None,
    scale: float = 1.0,
    motion: str = "rom",
    noise_mm: float = 0.0,
    soft_tissue_mm: float = 0.0,
    subject_seed: int | None = None,
    hinge_slack_deg: tuple[float, float] = (5.0, 12.0),
) -> SynthTake:
    """A seeded take of a 15-segment human with 48 skin markers and its truth.

    Lab frame: Z up, mm; the subject faces +X at rest, +Y is its left, the
    floor is ``z = 0`` (see the module docstring for the body and markers).

    Parameters
    ----------
    rng : numpy.random.Generator
        The only source of randomness. Three seeds are drawn from it (subject,
        motion, noise), so the same generator state gives the same subject for
        every ``motion``, ``n_frames`` and noise setting.
    n_frames : int
        Number of frames F (at least 2).
    rate : float
        Frames per second.
    markers_per_segment : int, sequence of 15 ints or {segment name: int}, optional
        Markers on each segment (at least 1). Default (None): pelvis, torso
        and head 4, limb segments 3 — 48 markers. A mapping overrides the
        default for the segments it names.
    scale : float
        Multiplies every length of the subject (not the capture volume).
    motion : {"rom", "walk"}
        ``"rom"``: range of motion; the joint groups (spine+neck, each arm,
        each leg) take turns moving through their full ranges (every ball-joint
        DoF covers ≥ 20°, the hinges ≥ 115°) while the pelvis wanders
        ±800 mm over the floor, turns ±150° and tilts. ``"walk"``: walking at
        ~1.1 m/s round a wobbly circle of ~1.5 m radius, smaller joint
        amplitudes (feet are not pinned to the floor).
    noise_mm : float
        Standard deviation of white Gaussian noise added to every coordinate.
    soft_tissue_mm : float
        RMS length of the smooth (1–5 Hz) skin displacement of each marker,
        30 % of its variance shared by the markers of a segment.
    subject_seed : int, optional
        Fix the subject (proportions, marker placement) regardless of ``rng``,
        e.g. ``take.truth.info["subject_seed"]`` of another take, to make
        several takes of one subject.
    hinge_slack_deg : (2,) floats
        Half-ranges (deg) of the off-axis rotation of elbows and knees:
        varus/valgus and axial. They make the joint centre along the flexion
        axis observable (as on real knees); (0, 0) gives pure hinges. In
        ``"walk"`` the slack used is 30 % of this.

    Returns
    -------
    SynthTake
        ``markers.points`` : (F, M, 3) float64 mm, no gaps. ``truth.joints`` :
        (F, 14, 3) exact joint centres (joint ``e`` has child segment
        ``e + 1``); ``truth.bone_length`` : (14,) distance from the joint to the
        mean of the child segment's own child joints (NaN for Head, hands and
        feet). ``truth.info`` holds ``joint_names``, ``hinges``,
        ``hinge_axes``, ``rest_joints_mm`` (14, 3) and ``rest_markers_mm``
        (M, 3) in the body frame at rest (pelvis centre at the origin, lab
        axes), ``physical_labels``, the seeds and settings.
    """
    if motion not in MOTIONS:
        raise ValueError(f"motion must be one of {MOTIONS}, got {motion!r}")
    n_frames = _check_take_args(n_frames, rate, scale, noise_mm, soft_tissue_mm)
    counts = _marker_counts(markers_per_segment)
    seeds = rng.integers(0, 2**63 - 1, size=3)
    sseed = int(seeds[0]) if subject_seed is None else int(subject_seed)
    mseed, nseed = int(seeds[1]), int(seeds[2])

    subj = _make_subject(sseed, counts, float(scale))
    t = np.arange(n_frames) / float(rate)
    mrng = np.random.default_rng(mseed)
    slack = np.array(hinge_slack_deg, dtype=float)
    if slack.shape != (2,) or (slack < 0).any():
        raise ValueError(f"hinge_slack_deg must be two non-negative angles, got {hinge_slack_deg}")
    root_pos, root_rot, rv = (_rom_motion if motion == "rom" else _walk_motion)(mrng, t, subj, slack)
    G, O, pts = _forward(subj, root_pos, root_rot, rv)
    if motion == "walk":  # lower or raise the body so that the lower foot touches the floor
        lift = _floor_lift(subj, G, O)
        O[..., 2] += lift[:, None]
        pts[..., 2] += lift[:, None]
    del G

    nrng = np.random.default_rng(nseed)
    if soft_tissue_mm > 0:
        pts += _soft_tissue(nrng, n_frames, subj.marker_segment, float(rate), float(soft_tissue_mm))
    if noise_mm > 0:
        pts += nrng.normal(0.0, float(noise_mm), pts.shape)

    joint_child = np.arange(1, _S)
    joints = O[:, 1:].copy()
    bone = np.full(_S - 1, np.nan)
    for e, c in enumerate(joint_child):
        kids = np.flatnonzero(PARENT == c)
        if kids.size:
            bone[e] = np.linalg.norm(subj.joint_rest[kids].mean(0) - subj.joint_rest[c])
    M = subj.marker_rest.shape[0]
    hinge_axes = {h: _hinge_frame(h)[0].tolist() for h in HINGES}
    info = {
        "kind": "human",
        "motion": motion,
        "subject_seed": sseed,
        "motion_seed": mseed,
        "noise_seed": nseed,
        "n_frames": n_frames,
        "rate": float(rate),
        "scale": float(scale),
        "markers_per_segment": list(counts),
        "noise_mm": float(noise_mm),
        "noise_mm_is": "standard deviation per coordinate",
        "soft_tissue_mm": float(soft_tissue_mm),
        "soft_tissue_mm_is": "RMS length of each marker's 3-D skin displacement",
        "soft_tissue_band_hz": list(_SOFT_TISSUE_BAND_HZ),
        "lab_up": "z",
        "lab_frame": "right-handed, Z up, mm; subject faces +X at rest, +Y is its left, floor z=0",
        "joint_names": list(JOINT_NAMES),
        "ball_joints": [j for j in JOINT_NAMES if j not in HINGES],
        "hinges": list(HINGES),
        "hinge_axes": hinge_axes,
        "hinge_off_axis_deg": {h: slack.tolist() for h in HINGES},
        "bone_length_is": "distance from the joint to the mean of the child segment's child joints",
        "part_factor": subj.part_factor,
        "pelvis_height_mm": subj.pelvis_height,
        "rest_joints_mm": subj.joint_rest[1:].tolist(),
        "rest_markers_mm": subj.marker_rest.tolist(),
        "physical_labels": list(subj.labels),
    }
    markers = Markers(
        points=pts,
        labels=subj.labels,
        rate=float(rate),
        units="mm",
        source=f"synth-human-{motion}",
        stage="read",
        info={},
    )
    truth = Truth(
        segment_names=SEGMENTS,
        parent=PARENT.copy(),
        marker_segment=subj.marker_segment.copy(),
        marker_id=np.arange(M),
        joint_child=joint_child,
        joints=joints,
        bone_length=bone,
        info=info,
    )
    return SynthTake(markers=markers, truth=truth)
