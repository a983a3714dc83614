"""``mocapskel compare``: how alike two fitted skeletons are (same subject or not)."""
from __future__ import annotations

import json

import click
import numpy as np

from ..batch import SAME_SUBJECT_PCT, Bones, Comparison, compare_bones
from ..errors import InputError
from .main import cli
from .options import common


def load_report(path: str) -> Bones:
    """The skeleton of a fit report JSON (InputError when it is missing, unreadable or not a report)."""
    from ..io.paths import require_regular_file

    p = require_regular_file(path, "the report JSON written by 'fit --report' or 'batch'")
    try:
        rep = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError, RecursionError) as e:
        raise InputError(f"not a JSON report ({type(e).__name__}) — give the JSON written by 'fit --report' or 'batch'", path) from None
    return Bones.from_report(rep, path)


def _num(x: float, digits: int = 1) -> str:
    return f"{x:.{digits}f}" if np.isfinite(x) else "-"


def format_comparison(c: Comparison, name_a: str = "A", name_b: str = "B") -> str:
    """The text ``compare`` prints: bones side by side, relative differences, distance, verdict."""
    a, b = c.a, c.b
    lines = [f"A: {name_a} ({a.n} segments)", f"B: {name_b} ({b.n} segments)"]
    if c.mapping is None:
        lines.append("the skeletons have different topologies: their bones cannot be matched")
        lines.append("same subject: unlikely (different topologies)")
        return "\n".join(lines)
    m = c.mapping
    lines.append(f"bones matched by {'marker labels' if c.matched_by == 'labels' else 'tree structure'}")
    used = c.used
    kept = used.copy()
    if c.left_out >= 0:
        kept[c.left_out] = False
    tot_a = a.length[kept].sum() if kept.any() else np.nan
    tot_b = b.length[m][kept].sum() if kept.any() else np.nan
    wa = max(4, *(len(n) for n in a.names))
    wb = max(4, *(len(n) for n in b.names))
    lines.append(f"{'A':<{wa}}  {'B':<{wb}}  {'A mm':>8}  {'B mm':>8}  {'A %':>6}  {'B %':>6}  {'diff %':>7}")
    for i in range(a.n):
        j = int(m[i])
        la, lb = a.length[i], b.length[j]
        if used[i]:
            pa, pb = 100 * la / tot_a, 100 * lb / tot_b
            tail = f"{_num(pa, 2):>6}  {_num(pb, 2):>6}  {100 * c.relative_difference[i]:>+7.2f}"
            if i == c.left_out:
                tail += "  (the largest difference: left out of the distance)"
        else:
            why = "end site" if not a.inner[i] else "no length"
            tail = f"{'':>6}  {'':>6}  {'':>7}  ({why}, not compared)"
        lines.append(f"{a.names[i]:<{wa}}  {b.names[j]:<{wb}}  {_num(la):>8}  {_num(lb):>8}  {tail}")
    if np.isfinite(c.distance_pct):
        lines.append(f"size B/A: {c.scale:.3f} (total of the {int(kept.sum())} bones kept; proportions ignore size)")
        lines.append(f"proportion distance: {c.distance_pct:.2f} % (same subject at most {c.threshold_pct:.2f} %)")
        lines.append(f"same subject: {'likely' if c.same_subject else 'unlikely'}")
    else:
        lines.append("proportion distance: - (fewer than two bones with a length in both)")
        lines.append("same subject: unlikely (nothing to compare)")
    return "\n".join(lines)


@cli.command("compare")
@click.argument("report_a", type=click.Path(dir_okay=False))
@click.argument("report_b", type=click.Path(dir_okay=False))
@click.option("--threshold", "threshold_pct", type=click.FloatRange(min=0.0), default=SAME_SUBJECT_PCT,
              show_default=True, help="Proportion distance (percent) up to which the subject is likely the same.")
@common
def compare_cmd(report_a, report_b, threshold_pct):
    """Say how alike two fitted skeletons are: bone lengths, proportions, same subject or not.

    REPORT_A and REPORT_B are report JSONs (from 'fit --report' or 'batch').
    Bones are matched by their segments' marker labels, or else by the tree.
    Joint-to-joint bones are normalised by their total (so overall size does
    not count) and compared; the proportion distance is the length-weighted
    RMS of their relative differences, leaving out the bone that differs most
    when five or more are compared (one badly fitted joint does not decide).
    Exit code 0 whatever the verdict, 3 for a file that is not a report.

    \b
    Example:
        mocapskel compare out/monday.json out/tuesday.json
    """
    a = load_report(report_a)
    b = load_report(report_b)
    c = compare_bones(a, b, threshold_pct)
    click.echo(format_comparison(c, report_a, report_b))
