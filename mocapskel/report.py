"""The JSON report of a fit: what went in, what each stage did, how good the result is."""
from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from . import __version__
from .artifacts import Motion, markers_of
from .model.measures import visible


def _f(x: Any) -> Any:
    """JSON-safe float (NaN/inf become None)."""
    if x is None:
        return None
    x = float(x)
    return x if np.isfinite(x) else None


def build_report(run: Any, params: dict[str, Any]) -> dict:
    """Assemble the report from the Motion artifact of a run (see README: report fields)."""
    motion: Motion = run.artifact
    skel = motion.skeleton
    joints = skel.joints
    topo = joints.topology if joints is not None else None
    segs = topo.segments if topo is not None else None
    mk = markers_of(motion)
    pts = mk.points
    vis = visible(pts)
    read_info = {k: v for k, v in mk.info.items() if k not in ("clean", "merge_ids")}
    warnings: list[str] = list(run.warnings)
    for v in mk.info.get("warnings", []) or []:
        warnings.append(str(v))
    rep: dict[str, Any] = {
        "tool": {"name": "mocapskel", "version": __version__},
        "input": {
            "file": mk.source,
            "frames": mk.n_frames,
            "markers": mk.n_markers,
            "rate_hz": _f(mk.rate),
            "source_units": mk.units,
            "visible_fraction": _f(vis.mean()) if vis.size else None,
            "read": read_info,
        },
        "clean": mk.info.get("clean", {}),
        "merge_ids": mk.info.get("merge_ids", {}),
        "params": {k: dataclasses.asdict(v) for k, v in params.items() if dataclasses.is_dataclass(v)},
    }
    if segs is not None:
        rep["segments"] = [
            {"index": s, "name": skel.names[s], "markers": [mk.labels[i] for i in segs.members(s)]}
            for s in range(segs.n_segments)
        ]
        rep["segments_left_out"] = [mk.labels[i] for i in np.flatnonzero(segs.group < 0)]
        rep["segments_moved"] = list(segs.info.get("moved", []))
        rep["segments_split"] = list(segs.info.get("split_nonrigid", []))
        rep["segments_computed"] = list(segs.info.get("computed", []))
        warnings.extend(w for w in segs.info.get("warnings", []) if w not in warnings)
    if topo is not None:
        rep["topology"] = {
            "root": skel.names[topo.root],
            "edges": [
                {"parent": skel.names[a], "child": skel.names[b], "joint_cost_mm2": _f(c)}
                for (a, b), c in zip(topo.edges.tolist(), topo.cost.tolist())
            ],
        }
        rep["joints"] = [
            {
                "parent": skel.names[a],
                "child": skel.names[b],
                "method": joints.method[e],
                "residual_mm": _f(joints.residual[e]),
                **(joints.info.get("per_joint", [{}] * len(joints.method))[e] if joints.info.get("per_joint") else {}),
            }
            for e, (a, b) in enumerate(topo.edges.tolist())
        ]
        warnings.extend(joints.info.get("warnings", []))
    links = skel.info.get("links", [])
    if links:
        rep["links"] = links
    for k in links:
        # the joints stage's one joint is now the link's joint with the child; the link's joint with the parent is new
        for entry in rep.get("joints", []):
            if entry["parent"] == k["parent"] and entry["child"] == k["child"]:
                entry.update(parent=k["segment"], link=k["segment"])
        rep.setdefault("joints", []).append({"parent": k["parent"], "child": k["segment"], "method": "link",
                                             "residual_mm": None, "link": k["segment"]})
        warnings.append(f"joint {k['parent']}–{k['child']}: two joints with a link of no markers between them ({k['segment']},"
                        f" {k['length_mm']:.0f} mm), in place of one joint: one joint left the two segments' motion"
                        f" {k['one_joint_rms_mm']:.0f} mm rms off one point, the link {k['sphere_rms_mm']:.1f} mm off its sphere")
    rep["bones"] = [
        {"segment": skel.names[s], "parent": skel.names[p] if p >= 0 else None, "length_mm": _f(skel.bone_length[s]),
         "rigid_fit_rms_mm": _f(skel.noise[s])}
        for s, p in enumerate(skel.parent.tolist())
    ]
    rep["rest_frame"] = int(skel.rest_frame)
    ref = skel.info.get("refined")
    rep["refinement"] = {k: (_f(v) if isinstance(v, float) else v) for k, v in ref.items()} if ref else None
    rep["ik"] = {
        "marker_rms_mm": _f(motion.info.get("rms_mm")),
        "marker_rms_mm_per_segment": {k: _f(v) for k, v in motion.info.get("rms_mm_per_segment", {}).items()},
        "filled_fraction": _f(motion.info.get("filled_fraction")),
        "out_of_view_frames": motion.info.get("out_of_view_frames", {}),
        "unflip": motion.info.get("unflip"),
    }
    warnings.extend(w for w in motion.info.get("warnings", []) if w not in warnings)
    rep["seconds"] = {k: round(float(v), 4) for k, v in run.seconds.items()}
    rep["cached_stages"] = list(run.cached)
    rep["warnings"] = warnings
    return rep


#: What a subject does so that the markers place a joint they left to the prior (humanoid joints): the
#: joint turned about another axis than the one it turned about.
MOTION_TO_FIX: dict[str, str] = {
    "Hip": "turn the thigh sideways (abduction) and about its own axis as well as forward",
    "Knee": "turn the shank about its own axis (the foot in and out) with the knee bent, as well as bending it",
    "Ankle": "turn the foot in and out (inversion) as well as up and down",
    "Toe": "bend the toes sideways as well as up and down",
    "Shoulder": "raise the arm sideways and turn it about its own axis as well as forward",
    "Elbow": "turn the forearm (palm up, palm down) with the elbow bent, as well as bending it",
    "Wrist": "bend the hand sideways as well as up and down",
    "Sternoclavicular": "shrug the shoulder up and down as well as forward and back",
    "Lumbar": "bend the trunk sideways and twist it as well as forward",
    "Thoracic": "bend the chest sideways and twist it as well as forward",
    "UpperThoracic": "bend the chest sideways and twist it as well as forward",
    "LowerNeck": "tilt the head sideways and turn it as well as nodding",
    "Neck": "tilt the head sideways and turn it as well as nodding",
    "UpperNeck": "tilt the head sideways and turn it as well as nodding",
}


def _axis_words(v: Any) -> str:
    return "(" + ", ".join(f"{float(x):.2f}" for x in v) + ")"


def add_uncertainty(report: dict, skel: Any, naming: Any = None) -> None:
    """Each joint's uncertainty (the rigid stage's ``info["uncertainty"]``) into the report's joints, the
    prior and the take's noise into ``report["uncertainty"]``, and a warning for every joint the prior
    sets, with the motion that would place it (in words for a humanoid's joints, else as an axis)."""
    unc = skel.info.get("uncertainty") if skel is not None else None
    if not unc:
        report["uncertainty"] = None
        return
    report["uncertainty"] = {k: v for k, v in unc.items() if k != "joints"}
    humanoid = naming is not None and getattr(naming, "humanoid", False)
    names = list(skel.names)
    warnings = report.setdefault("warnings", [])
    for entry in report.get("joints", []):
        got = unc["joints"].get(entry.get("child"))
        if got is None:
            continue
        got = dict(got)
        c = names.index(entry["child"])
        jname = naming.joint_names[c] if naming is not None and c < len(naming.joint_names) else ""
        jname = jname or f"{entry['parent']}-{entry['child']}"
        words = None
        if got["set_by_prior"]:
            axis = _axis_words(got["lacks_rotation_about"])
            base = jname.removeprefix("Left").removeprefix("Right")
            words = MOTION_TO_FIX.get(base) if humanoid else None
            if words is None:
                child = naming.names[c] if naming is not None else entry["child"]
                words = f"turn {child} about {axis} (lab axes at the rest frame) as well"
            else:
                words = f"{words} (a turn about {axis}, lab axes at the rest frame)"
            i = int(np.argmax(got["prior_share"]))
            if sum(float(x) > 0.5 for x in got["prior_share"]) >= 2:  # free along two directions: it hardly turned
                words = f"turn it more, about two axes across each other: {words}"
            turned = got.get("turned_about")
            warnings.append(
                f"joint {jname} is set by the prior along {_axis_words(got['directions'][i])}: sd {got['sd_mm'][i]:.0f} mm,"
                f" {got['prior_share'][i]:.0%} of its precision from the prior"
                + (f" (its turns in the take were mostly about {_axis_words(turned)})" if turned is not None else "")
                + f"; to place it, {words}")
        got["motion_to_fix"] = words
        entry["uncertainty"] = got
