"""``mocapskel fit``: the whole pipeline, from a take to BVH."""
from __future__ import annotations

import json
import logging

import click

from .. import pipeline
from ..io.atomic import atomic_open
from ..io.bvh import write_bvh
from .main import cli
from .options import bvh_options, cache_options, check_output, common, fit_options, make_cache, make_read, read_options

log = logging.getLogger("mocapskel")


def write_report(path, report: dict) -> None:
    with atomic_open(path, "w", encoding="utf-8") as f:
        json.dump(report, f, indent=2, allow_nan=False)
        f.write("\n")


@cli.command("fit")
@click.argument("input", type=click.Path(dir_okay=True))
@click.option("-o", "--output", "output", required=True, type=click.Path(), help="BVH file to write.")
@fit_options
@bvh_options
@click.option("--report", "report_path", type=click.Path(), default=None, help="Also write the JSON report here.")
@read_options
@cache_options
@common
def fit_cmd(input, output, segments, joint_method, rest_frame, up, units, report_path, exclude, include, cache_dir, no_cache):
    """Fit a skeleton to a take (C3D or TRC) and write its motion as BVH.

    \b
    Examples:
        mocapskel fit take.c3d -o take.bvh
        mocapskel fit take.trc -o take.bvh --up z --units mm --report take.json
    """
    check_output(output, input, suffixes=(".bvh",))
    if report_path:
        check_output(report_path, input, suffixes=(".json",))
    params = pipeline.make_params(segments=segments, joint_method=joint_method, rest_frame=rest_frame, up=up, units=units)
    res = pipeline.fit(input, params, cache=make_cache(cache_dir, no_cache), read=make_read(exclude, include))
    b = res.bvh
    write_bvh(output, b.skeleton, b.root_pos, b.local_rot, b.frame_time)
    if report_path:
        write_report(report_path, res.report)
    ik = res.report["ik"]
    rms = ik.get("marker_rms_mm")
    log.info(
        "wrote %s: %d segments, %d frames, marker rms %s mm (%.1f s)",
        output, len(b.skeleton.names), b.root_pos.shape[0],
        f"{rms:.2f}" if rms is not None else "n/a", res.run.seconds.get("total", 0.0),
    )
    for w in res.report.get("warnings", []):
        log.warning("warning: %s", w)
