"""The HTML report: its data (decimated, rounded, residual series), the page, the CLI, and the page in a browser."""
from __future__ import annotations

import base64
import dataclasses
import json
import math
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

pytest.importorskip("matplotlib", reason="the HTML report needs matplotlib (mocapskel[report])")

from mocapskel import artifacts, pipeline  # noqa: E402
from mocapskel.cache import Cache  # noqa: E402
from mocapskel.cli.main import cli  # noqa: E402
from mocapskel.evaluate import joint_positions  # noqa: E402
from mocapskel.html_report.data import joint_residual_series, segment_residual_series  # noqa: E402
from mocapskel.html_report.page import build_html  # noqa: E402
from mocapskel.html_report.plots import MAX_PLOT_SAMPLES, _reduce  # noqa: E402
from mocapskel.html_report.viewer import _json_for_script, viewer_data  # noqa: E402
from mocapskel.io.markers import write_markers  # noqa: E402
from mocapskel.synth.presets import Recipe, make  # noqa: E402
from mocapskel.io import artifact_files

SECTIONS = ("summary", "warnings", "view", "segments", "topology", "joint-residual", "ik-residual", "bones", "uncertainty")
CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")


def run(*args):
    r = CliRunner().invoke(cli, [str(a) for a in args])
    return r.exit_code, r.stdout, r.stderr


@pytest.fixture(scope="module")
def human(tmp_path_factory):
    """A short human take with noise, soft tissue and gaps, written as C3D, and its fit."""
    d = tmp_path_factory.mktemp("html")
    take = make(Recipe(kind="human", frames=600, noise_mm=1.0, soft_tissue_mm=1.0, gaps_per_marker_per_minute=4, seed=5))
    write_markers(d / "human.c3d", take.markers)
    res = pipeline.fit(d / "human.c3d", pipeline.make_params(), cache=Cache(d / "cache"))
    artifact_files.save(res.motion, d / "human_ik.npz")
    return d, res


@pytest.fixture(scope="module")
def page(human):
    _, res = human
    return build_html(res.motion, res.report)


# --------------------------------------------------------------------------- data


def test_viewer_data_is_decimated_and_rounded_to_a_tenth_of_a_mm(human):
    _, res = human
    m = res.motion
    F = m.root_pos.shape[0]
    data = viewer_data(m, max_frames=100)
    step = math.ceil(F / 100)
    assert data["step"] == step and data["n"] == len(range(0, F, step)) <= 100
    assert data["frames"] == F and data["quantum_mm"] == 0.1
    M, S = len(data["labels"]), len(data["names"])
    assert M == m.skeleton.marker_segment.size and S == m.rot.shape[1]
    for key, width in (("markers", 3 * M), ("joints", 3 * S), ("ends", 3 * len(data["leaves"]))):
        assert len(data[key]) == data["n"]
        assert all(len(row) == width for row in data[key])
        assert all(v is None or isinstance(v, int) for row in data[key] for v in row)
    # dequantised joints are the IK joint positions of the kept frames, to 0.05 mm
    jp = joint_positions(m)[::step]
    got = np.array(data["joints"], dtype=float).reshape(data["n"], S, 3) * 0.1 + np.array(data["origin"])
    assert np.abs(got - jp).max() <= 0.05 + 1e-9
    # a marker that is not seen is null, one that is seen is within 0.05 mm
    pts = artifacts.markers_of(m).points[::step]
    mk = np.array([[np.nan if v is None else v for v in row] for row in data["markers"]]).reshape(data["n"], M, 3)
    mk = mk * 0.1 + np.array(data["origin"])
    assert np.array_equal(np.isnan(mk), np.isnan(pts))
    assert np.nanmax(np.abs(mk - pts)) <= 0.05 + 1e-9
    # short takes are kept whole
    assert viewer_data(m, max_frames=10 * F)["step"] == 1


def test_joint_residual_is_zero_for_a_noise_free_chain(chain433):
    res = pipeline.fit(chain433.markers, pipeline.make_params())
    jr = joint_residual_series(res.motion)
    assert jr.shape == (chain433.markers.n_frames, 2)
    assert np.nanmax(jr) < 1e-6 * 300.0


def test_joint_residual_over_time_agrees_with_the_reported_joint_residual(human):
    _, res = human
    m = res.motion
    jr = joint_residual_series(m)
    E = m.skeleton.joints.topology.edges.shape[0]
    assert jr.shape == (m.root_pos.shape[0], E)
    assert np.isfinite(jr).mean() > 0.9
    rms = np.sqrt(np.nanmean(jr**2, axis=0))
    np.testing.assert_allclose(rms, m.skeleton.joints.residual, rtol=0.1)


def test_segment_residual_marks_gaps_where_a_marker_is_missing(human):
    _, res = human
    m = res.motion
    rms, gap = segment_residual_series(m)
    S = m.rot.shape[1]
    assert rms.shape == gap.shape == (m.root_pos.shape[0], S)
    for s in range(S):
        idx = np.flatnonzero(m.skeleton.marker_segment == s)
        seen = np.isfinite(m.residual[:, idx])
        np.testing.assert_array_equal(gap[:, s], ~seen.all(axis=1))
        full = seen.all(axis=1)
        np.testing.assert_allclose(rms[full, s], np.sqrt(np.mean(m.residual[full][:, idx] ** 2, axis=1)))
    assert gap.any(), "the take has gaps: some must be shaded"
    # the per-segment rms over the take is the report's
    per_seg = res.report["ik"]["marker_rms_mm_per_segment"]
    for s, name in enumerate(m.skeleton.names):
        r = m.residual[:, m.skeleton.marker_segment == s]
        assert per_seg[name] == pytest.approx(float(np.sqrt(np.nanmean(r**2))))


def test_long_series_are_binned_keeping_rms_and_spikes():
    rng = np.random.default_rng(0)
    F = 60_000
    t = np.arange(F) / 120.0
    y = np.abs(rng.normal(2.0, 0.5, F))
    y[12_345] = 40.0  # a planted spike
    y[30_000:30_100] = np.nan  # a gap
    gap = ~np.isfinite(y)
    tt, rms, lo, hi, gg = _reduce(t, y, gap)
    assert tt.size == rms.size == lo.size == hi.size == gg.size <= MAX_PLOT_SAMPLES
    b = math.ceil(F / MAX_PLOT_SAMPLES)
    assert hi[12_345 // b] == 40.0 and np.nanmax(np.delete(hi, 12_345 // b)) < 40.0
    assert gg[30_000 // b] and gg.sum() == len(range(30_000 // b, (30_099 // b) + 1))
    assert np.all((lo <= rms + 1e-12) | np.isnan(rms)) and np.all((rms <= hi + 1e-12) | np.isnan(rms))
    assert np.sqrt(np.nanmean(rms**2)) == pytest.approx(np.sqrt(np.nanmean(y**2)), rel=1e-3)
    # short series are left alone
    t2, y2, lo2, hi2, _ = _reduce(t[:100], y[:100])
    assert np.array_equal(y2, y[:100]) and lo2 is None and hi2 is None


def test_json_in_a_script_element_cannot_close_it():
    text = _json_for_script({"label": "</script><!-- & >"})
    assert "</" not in text and "<!--" not in text and "&" not in text
    assert json.loads(text) == {"label": "</script><!-- & >"}


# --------------------------------------------------------------------------- the page


def test_page_is_self_contained_and_has_every_section(page, human):
    _, res = human
    for sid in SECTIONS:
        assert f'<section id="{sid}">' in page
    # nothing from elsewhere: no external scripts, styles, fonts or images
    low = page.lower()
    for bad in ("http://", "https://", "<script src", "<link", "@import", "url("):
        assert bad not in low, bad
    imgs = re.findall(r'<img class="plot[^"]*" alt="[^"]*" src="data:image/png;base64,([A-Za-z0-9+/=]+)">', page)
    assert len(imgs) == 6  # distance-std matrix, eigen-gap, segment graph, joint residual, IK residual, joint uncertainty
    for b in imgs:
        assert base64.b64decode(b)[:8] == b"\x89PNG\r\n\x1a\n"
    data = json.loads(re.search(r'<script type="application/json" id="viewer-data">(.*?)</script>', page, re.S).group(1))
    assert data["n"] == res.motion.root_pos.shape[0]  # 600 frames: not decimated
    # the tables
    for b in res.report["bones"]:
        assert f"{b['segment']}</td>" in page
    assert page.count("<tr>") >= len(res.report["bones"]) + len(res.report["joints"])
    assert "No warnings." in page or "<ul class=\"warnings\">" in page


def test_warnings_are_listed_and_escaped_and_long_takes_decimated(human):
    _, res = human
    rep = dict(res.report, warnings=["joint <A>-B poorly determined"])
    text = build_html(res.motion, rep, max_frames=50)
    assert "Warnings (1)" in text and "joint &lt;A&gt;-B poorly determined" in text
    data = json.loads(re.search(r'id="viewer-data">(.*?)</script>', text, re.S).group(1))
    assert data["n"] <= 50 and data["step"] == math.ceil(res.motion.root_pos.shape[0] / 50)


def test_groups_split_for_rigidity_are_listed_and_escaped(human):
    _, res = human
    split = [{"parts": [["C7", "T10", "<CLAV>"], ["LBWT", "RBWT", "LTHI"]], "rigid_rms_mm": 6.702}]
    text = build_html(res.motion, dict(res.report, segments_split=split), max_frames=50)
    assert "did not move as one body (6.7 mm rigid-fit rms) split into C7 T10 &lt;CLAV&gt; | LBWT RBWT LTHI" in text
    assert "did not move as one body" not in build_html(res.motion, dict(res.report, segments_split=[]), max_frames=50)


def test_segments_out_of_view_are_listed_with_their_share_of_the_take(human):
    _, res = human
    frames = res.report["input"]["frames"]
    ik = dict(res.report["ik"], out_of_view_frames={"<seg05>": frames // 4})
    text = build_html(res.motion, dict(res.report, ik=ik), max_frames=50)
    assert f"&lt;seg05&gt; {frames // 4} frames (25 %)" in text and "made up" in text
    ik = dict(res.report["ik"], out_of_view_frames={})
    assert "made up" not in build_html(res.motion, dict(res.report, ik=ik), max_frames=50)


def test_a_motion_without_its_fit_chain_still_gets_a_page(human):
    """A skeleton read from a .skel file carries no joints, segments or markers: those sections say so."""
    _, res = human
    m = dataclasses.replace(res.motion, skeleton=dataclasses.replace(res.motion.skeleton, joints=None))
    text = build_html(m, {"input": {"file": "take.c3d"}, "warnings": []})
    for sid in SECTIONS:
        assert f'<section id="{sid}">' in text
    assert "carries no segmentation" in text and "carries no topology" in text and "carries no joint centres" in text
    assert json.loads(re.search(r'id="viewer-data">(.*?)</script>', text, re.S).group(1))["labels"] == []


# --------------------------------------------------------------------------- command line


def test_report_command_from_a_take_and_from_an_ik_artifact(human, tmp_path):
    d, _ = human
    code, _, err = run("report", d / "human.c3d", "-o", tmp_path / "take.html", "--cache-dir", d / "cache")
    assert code == 0, err
    assert "ik        cached — skipping" in err  # the same fit as the fixture's
    text = (tmp_path / "take.html").read_text(encoding="utf-8")
    assert text.startswith("<!DOCTYPE html>") and all(f'id="{s}"' in text for s in SECTIONS)
    assert "HTML report" in err
    code, _, err = run("report", d / "human_ik.npz", "-o", tmp_path / "ik.html", "--no-cache")
    assert code == 0, err
    assert all(f'id="{s}"' in (tmp_path / "ik.html").read_text(encoding="utf-8") for s in SECTIONS)
    assert not list(tmp_path.glob(".*.part"))


def test_fit_html_writes_the_report_beside_the_bvh(human, tmp_path):
    d, _ = human
    code, _, err = run("fit", d / "human.c3d", "-o", tmp_path / "t.bvh", "--html", tmp_path / "t.html", "--cache-dir", d / "cache")
    assert code == 0, err
    assert (tmp_path / "t.bvh").exists()
    assert '<canvas id="viewer"' in (tmp_path / "t.html").read_text(encoding="utf-8")


def test_report_refuses_a_bad_output_before_fitting(human, tmp_path):
    d, _ = human
    code, _, err = run("report", d / "human_ik.npz", "-o", tmp_path / "r.json")
    assert code == 2 and "should end in .html" in err
    code, _, err = run("report", d / "human_ik.npz", "-o", tmp_path / "missing" / "r.html")
    assert code == 2 and "does not exist" in err
    code, _, err = run("fit", d / "human.c3d", "-o", tmp_path / "t.bvh", "--html", tmp_path / "t.txt")
    assert code == 2 and not (tmp_path / "t.bvh").exists()
    code, _, err = run("report", tmp_path / "nope.c3d", "-o", tmp_path / "r.html")
    assert code == 3 and not (tmp_path / "r.html").exists()


def test_missing_matplotlib_is_one_line_exit_2(human, tmp_path, monkeypatch):
    d, _ = human
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib now raises ImportError
    code, _, err = run("report", d / "human_ik.npz", "-o", tmp_path / "r.html")
    assert code == 2
    assert "install mocapskel[report]" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "r.html").exists()
    code, _, err = run("fit", d / "human.c3d", "-o", tmp_path / "t.bvh", "--html", tmp_path / "t.html", "--no-cache")
    assert code == 2 and "install mocapskel[report]" in err
    assert not (tmp_path / "t.bvh").exists()


# --------------------------------------------------------------------------- in a browser


def _chromium() -> str | None:
    for name in CHROMIUM_NAMES:
        path = shutil.which(name)
        if path:
            return path
    return None


def _browser(binary: str, profile: Path, *args: str) -> subprocess.CompletedProcess:
    cmd = [
        binary, "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
        "--disable-component-update", "--disable-sync", "--no-first-run", "--hide-scrollbars",
        f"--user-data-dir={profile}", "--virtual-time-budget=5000", *args,
    ]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=180, stdin=subprocess.DEVNULL)


#: Appended to the page in the browser test: moves the slider, drags the view, plays for a second.
_HARNESS = """<script>
setTimeout(function () {
  var st = document.getElementById("viewer-status");
  var s = document.getElementById("viewer-slider");
  s.value = "300"; s.dispatchEvent(new Event("input"));
  st.setAttribute("data-afterslider", st.getAttribute("data-frame"));
  document.getElementById("viewer").dispatchEvent(new MouseEvent("mousedown", {clientX: 100, clientY: 100, bubbles: true}));
  window.dispatchEvent(new MouseEvent("mousemove", {clientX: 250, clientY: 160, bubbles: true}));
  window.dispatchEvent(new MouseEvent("mouseup", {bubbles: true}));
  document.getElementById("viewer-play").click();
  setTimeout(function () {
    st.setAttribute("data-afterplay", st.getAttribute("data-frame"));
    document.getElementById("viewer-play").click();
  }, 1000);
}, 100);
</script>
</body>"""


@pytest.mark.skipif(_chromium() is None, reason="headless Chromium is not installed (apt-get install chromium)")
def test_page_renders_in_headless_chromium_without_errors(page, human, tmp_path):
    _, res = human
    html_file = tmp_path / "report.html"
    html_file.write_text(page.replace("</body>", _HARNESS), encoding="utf-8")
    out = _browser(_chromium(), tmp_path / "profile", "--dump-dom", html_file.as_uri())
    assert out.returncode == 0, out.stderr[-2000:]
    m = re.search(r'<div id="viewer-status"([^>]*)>', out.stdout)
    assert m, "the page did not load: " + out.stdout[:500]
    attrs = dict(re.findall(r'data-([a-z]+)="([^"]*)"', m.group(1)))
    assert attrs["error"] == "", attrs["error"]
    assert attrs["ok"] == "1", "the 3-D view did not draw its first frame"
    mot = res.motion
    last = int(attrs["frame"])  # the frame drawn last
    seen = int(np.isfinite(artifacts.markers_of(mot).points[last]).all(-1).sum())
    assert int(attrs["points"]) == seen + mot.rot.shape[1]  # the markers seen + one point per joint
    n_leaves = int((np.linalg.norm(mot.skeleton.end_site, axis=1) > 0).sum())
    assert int(attrs["lines"]) == mot.rot.shape[1] - 1 + n_leaves  # bones + end sites
    n_img = page.count('<img class="plot')
    assert attrs["images"] == f"{n_img}/{n_img}", "a plot did not decode"
    if res.report.get("uncertainty"):  # every joint whose principal axes are drawn: three lines each
        assert int(attrs["unc"]) == 3 * len(viewer_data(mot)["unc"]["joints"])
    # the slider sets the frame; play advances it (about 1 s of the take at 120 Hz, every frame kept)
    assert attrs["afterslider"] == "300"
    assert 300 < int(attrs["afterplay"]) < 600
    assert "Uncaught" not in out.stderr

    shot = tmp_path / "report.png"
    out = _browser(_chromium(), tmp_path / "profile2", "--window-size=1280,1400", f"--screenshot={shot}", html_file.as_uri())
    assert out.returncode == 0 and shot.exists() and shot.stat().st_size > 10_000
