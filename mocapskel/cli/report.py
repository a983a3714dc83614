"""``mocapskel report``: a self-contained HTML report of a fit (plots, tables, animated 3-D view)."""
from __future__ import annotations

import logging
import os

import click

from .. import pipeline
from ..io.atomic import atomic_write_bytes
from .main import cli, say_warnings
from .options import cache_options, check_output, common, fit_options, make_cache, make_read, read_options

log = logging.getLogger("mocapskel")

HTML_SUFFIXES = (".html", ".htm")


def write_html_report(path: str | os.PathLike, result: pipeline.FitResult) -> int:
    """Build the HTML report of a fit and write it atomically to ``path``.

    Parameters
    ----------
    path : str or os.PathLike
        The HTML file to write.
    result : pipeline.FitResult
        The fit (its motion and JSON report).

    Returns
    -------
    int
        The size of the page in bytes.
    """
    from ..html_report import build_html

    data = build_html(result.motion, result.report).encode("utf-8")
    atomic_write_bytes(path, data)
    return len(data)


@cli.command("report")
@click.argument("input", type=click.Path(dir_okay=True))
@click.option("-o", "--output", "output", required=True, type=click.Path(), help="HTML file to write.")
@fit_options
@read_options
@cache_options
@common
def report_cmd(input, output, segments, joint_method, joint_model, rest_frame, exclude, include, cache_dir, no_cache):
    """Write a self-contained HTML report of a fit: plots, tables and an animated 3-D view.

    INPUT is a take (.c3d, .trc) or the .npz artifact of any stage (an ik
    artifact is reported as it is; earlier ones are run through the remaining
    stages, with the options of 'fit' that change the fit). The page holds the take's summary,
    the warnings, a 3-D view of markers and skeleton (play/pause, frame slider,
    drag to rotate), the marker-distance-std matrix and the eigen-gap, the
    segment graph with joint costs and the chosen tree, the joint and IK
    residuals over time and the bone lengths. It loads nothing from the network.
    Needs matplotlib: pip install 'mocapskel[report]'.

    \b
    Examples:
        mocapskel report take.c3d -o take.html
        mocapskel ik take.c3d -o take_ik.npz && mocapskel report take_ik.npz -o take.html
    """
    from ..html_report import require_matplotlib

    check_output(output, input, suffixes=HTML_SUFFIXES)
    require_matplotlib()
    params = pipeline.make_params(segments=segments, joint_method=joint_method, joint_model=joint_model, rest_frame=rest_frame)
    res = pipeline.fit(input, params, cache=make_cache(cache_dir, no_cache), read=make_read(exclude, include))
    size = write_html_report(output, res)
    log.info("wrote %s (HTML report, %.1f MB)", output, size / 1e6)
    say_warnings(res.report.get("warnings", []))
