"""``mocapskel fit``: the whole pipeline, from a take to BVH."""
from __future__ import annotations

import json
import logging
from pathlib import Path

import click

from .. import pipeline
from ..io.atomic import AtomicOutputs, atomic_open
from ..io.bvh import write_bvh
from .main import cli, say_warnings
from .options import (
    bvh_options,
    cache_options,
    check_output,
    common,
    fit_options,
    make_cache,
    make_read,
    naming_options,
    read_options,
    strict_option,
)

log = logging.getLogger("mocapskel")


def write_markers_out(path, motion, input_path, read, bvh=None, labels=None) -> None:
    """The take plus one virtual marker per joint centre, as C3D or TRC.

    From a C3D take to a C3D file: the input file itself with the joint points
    added (analogs, force plates, events, parameters kept). Otherwise the
    take's markers as read (only ``labels``, when given: one subject of
    several) plus the joint points.
    """
    from dataclasses import replace

    from ..io.markers import write_markers
    from ..model.joint_markers import joint_points, with_joint_markers

    naming = bvh.naming if bvh is not None else None
    if str(path).lower().endswith(".c3d") and str(input_path).lower().endswith(".c3d"):
        from ..io.c3d_points import FrameCountMismatch, add_points

        labels, desc, pts = joint_points(motion, naming)
        try:
            add_points(input_path, path, labels, desc, pts)
            return
        except FrameCountMismatch as e:  # a take longer than ezc3d reads (65535 frames)
            log.warning("warning: %s; --markers-out holds the markers and joint points only", e)
    markers, _ = pipeline.read_input(input_path, read)
    markers = pipeline.artifacts.markers_of(markers)
    if labels is not None:  # one subject of several
        keep = set(labels)
        idx = [i for i, l in enumerate(markers.labels) if l in keep]
        markers = replace(markers, points=markers.points[:, idx], labels=tuple(markers.labels[i] for i in idx))
    if markers.n_frames != motion.root_pos.shape[0]:  # pragma: no cover - same take
        raise ValueError("markers and motion differ in frame count")
    # keep only the labels the fit used, so that gaps and cleaning are as solved
    write_markers(path, with_joint_markers(markers, motion, naming))


def check_osim_out(path, input) -> tuple[str, str, str]:
    """``--osim-out SUBJECT.osim``: the model and, beside it, ``SUBJECT.trc`` (markers) and ``SUBJECT.mot``
    (coordinates); each must be a file that can be written and not the input."""
    from ..io.osim import osim_companions

    check_output(path, input, suffixes=(".osim",))
    trc, mot = osim_companions(path)
    for other in (trc, mot):
        check_output(other, input)
    return str(path), trc, mot


def osim_model(r, up: str):
    """The OpenSim model of one fit (``r``: a FitResult), its ``osim`` report entry set."""
    from ..solvers.osim_model import build_model

    source = r.report.get("input", {}).get("file") or ""
    model = build_model(r.motion, r.bvh.naming, up=up, name=Path(source).stem or "mocapskel")
    r.report["osim"] = model.report()
    return model


def write_osim_out(out, path, model, points, rate, source="") -> None:
    """Stage and write the .osim, .trc and .mot of ``--osim-out path``."""
    from ..io.osim import osim_companions, write_osim_outputs

    write_osim_outputs(tuple(out.stage(p) for p in (path, *osim_companions(path))), model, points, rate, source)


def write_outputs(out, output, gltf_path, b) -> None:
    """The motion as BVH (or glTF, by the output's extension), and as glTF too when asked."""
    for path in (output, gltf_path):
        if not path:
            continue
        if str(path).lower().endswith((".glb", ".gltf")):
            from ..io.gltf import write_gltf

            write_gltf(out.stage(path), b.skeleton, b.root_pos, b.local_rot, b.frame_time, up=b.up, units=b.units)
        else:
            write_bvh(out.stage(path), b.skeleton, b.root_pos, b.local_rot, b.frame_time)


def raise_if_strict(strict: bool, report: dict, source: str) -> None:
    """With ``--strict``, a failing output check is an error (exit code 4) before anything is written."""
    from ..checks import Finding, strict_error

    if strict and report.get("checks"):
        err = strict_error([Finding(c["check"], c["name"], c["message"]) for c in report["checks"]], str(source))
        raise err


def write_report(path, report: dict) -> None:
    with atomic_open(path, "w", encoding="utf-8") as f:
        json.dump(report, f, indent=2, allow_nan=False)
        f.write("\n")


@cli.command("fit")
@click.argument("input", type=click.Path(dir_okay=True))
@click.option("-o", "--output", "output", required=True, type=click.Path(), help="BVH file to write.")
@fit_options
@bvh_options
@naming_options
@click.option("--gltf", "gltf_path", type=click.Path(), default=None, help="Also write the skeleton and its motion as glTF 2.0 (.glb or .gltf).")
@click.option("--report", "report_path", type=click.Path(), default=None, help="Also write the JSON report here.")
@click.option("--skeleton-out", "skeleton_out", type=click.Path(), default=None, help="Also write the subject skeleton (.skel) for 'mocapskel solve'.")
@click.option("--markers-out", "markers_out", type=click.Path(), default=None, help="Also write the markers plus virtual joint markers (.c3d or .trc).")
@click.option("--osim-out", "osim_out", type=click.Path(), default=None,
              help="Also write an OpenSim model (.osim) and beside it its markers (.trc) and coordinates (.mot).")
@click.option("--html", "html_path", type=click.Path(), default=None, help="Also write the HTML report (plots, 3-D view) here; needs mocapskel[report].")
@strict_option
@read_options
@cache_options
@common
def fit_cmd(input, output, segments, joint_method, joint_model, rest_frame, up, units, names, rest, gltf_path, report_path, skeleton_out, markers_out, osim_out, html_path, strict, exclude, include, cache_dir, no_cache):
    """Fit a skeleton to a take (C3D or TRC) and write its motion as BVH.

    \b
    Examples:
        mocapskel fit take.c3d -o take.bvh
        mocapskel fit take.trc -o take.bvh --up z --units mm --report take.json
    """
    check_output(output, input, suffixes=(".bvh", ".glb", ".gltf"))
    if gltf_path:
        check_output(gltf_path, input, suffixes=(".glb", ".gltf"))
    if report_path:
        check_output(report_path, input, suffixes=(".json",))
    if skeleton_out:
        check_output(skeleton_out, input, suffixes=(".skel",))
    if markers_out:
        check_output(markers_out, input, suffixes=(".c3d", ".trc"))
    if osim_out:
        check_osim_out(osim_out, input)
    if html_path:
        from ..html_report import require_matplotlib
        from .report import HTML_SUFFIXES

        check_output(html_path, input, suffixes=HTML_SUFFIXES)
        require_matplotlib()
    params = pipeline.make_params(segments=segments, joint_method=joint_method, joint_model=joint_model, rest_frame=rest_frame, up=up, units=units,
                                  names=names, rest=rest)
    res = pipeline.fit(input, params, cache=make_cache(cache_dir, no_cache), read=make_read(exclude, include))
    for r in (res.subjects if len(res.subjects) > 1 else [res]):
        raise_if_strict(strict, r.report, input)
    several = len(res.subjects) > 1
    fits = res.subjects if several else [res]
    for r in fits:  # one subject: the names as given; several: OUT_1.bvh, OUT_2.bvh … and likewise every output
        r.report.setdefault("outputs", {})
        for what, path in (("bvh", output), ("gltf", gltf_path), ("report", report_path), ("skeleton", skeleton_out),
                           ("markers", markers_out), ("osim", osim_out), ("html", html_path)):
            if path:
                r.report["outputs"][what] = numbered(path, r.report["subject"]["index"]) if several else str(path)
        if several:
            for item in r.report["subjects"]:
                item["bvh"] = numbered(output, item["index"])
    models = [osim_model(r, up) for r in fits] if osim_out else [None] * len(fits)  # before any output: errors first
    if osim_out and several:
        for r in fits:
            check_osim_out(r.report["outputs"]["osim"], input)
    with AtomicOutputs() as out:  # every output appears at the end, or none does
        for r, model in zip(fits, models):
            o = r.report["outputs"]
            b = r.bvh
            write_outputs(out, o["bvh"], o.get("gltf"), b)
            if report_path:
                write_report(out.stage(o["report"]), r.report)
            if skeleton_out:
                from ..io.skeleton import write_skeleton

                write_skeleton(out.stage(o["skeleton"]), r.motion.skeleton, source=r.report["input"]["file"])
            if markers_out:
                labels = r.motion.skeleton.labels if several else None
                write_markers_out(out.stage(o["markers"]), r.motion, input, make_read(exclude, include), b, labels)
            if osim_out:
                write_osim_out(out, o["osim"], model, pipeline.artifacts.markers_of(r.motion).points, r.motion.rate,
                               r.report["input"]["file"])
            if html_path:
                from .report import write_html_report

                write_html_report(out.stage(o["html"]), r)
    for r in fits:
        b = r.bvh
        rms = r.report["ik"].get("marker_rms_mm")
        log.info(
            "wrote %s: %d segments, %d frames, marker rms %s mm (%.1f s)",
            r.report["outputs"]["bvh"], len(b.skeleton.names), b.root_pos.shape[0],
            f"{rms:.2f}" if rms is not None else "n/a", r.run.seconds.get("total", 0.0),
        )
    say_warnings([w for r in fits for w in r.report.get("warnings", [])])


def numbered(path, index: int) -> str:
    """``take.bvh`` → ``take_2.bvh``: the output of one subject of several."""
    p = Path(path)
    return str(p.with_name(f"{p.stem}_{index}{p.suffix}"))
