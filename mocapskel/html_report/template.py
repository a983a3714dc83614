"""The static text of the HTML report's page: its CSS, the page skeleton, and the 3-D view's controls and
JavaScript."""
from __future__ import annotations

# --------------------------------------------------------------------------- page template

_CSS = """
body{font:14px/1.45 system-ui,-apple-system,"Segoe UI",Roboto,Helvetica,Arial,sans-serif;margin:0;color:#222;background:#fafafa}
header{background:#263238;color:#fff;padding:10px 24px}header h1{font-size:20px;margin:4px 0}
nav{font-size:13px}nav a{color:#cfe3ff;text-decoration:none}
main{padding:8px 24px 40px;max-width:1240px}
section{background:#fff;border:1px solid #e3e3e3;border-radius:6px;padding:8px 16px 14px;margin:14px 0}
h2{font-size:17px;margin:6px 0 10px}
table{border-collapse:collapse;font-size:13px;margin:8px 0}
th,td{border-bottom:1px solid #e6e6e6;padding:3px 10px;text-align:left;vertical-align:top}
thead th{background:#f0f3f5}table.kv th{color:#555;font-weight:600;white-space:nowrap}
table.num td:nth-child(n+3){text-align:right;font-variant-numeric:tabular-nums}
img.plot{max-width:100%;height:auto;display:block;margin:6px 0}
.row{display:flex;flex-wrap:wrap;gap:1%;align-items:flex-start}.row img.dist{width:58%}.row img.eig{width:40%}
@media (max-width:900px){.row img.dist,.row img.eig{width:100%}}
.note{color:#555;font-size:12.5px}.ok{color:#2e7d32}
ul.warnings li{color:#b00020}
.chip{display:inline-block;width:11px;height:11px;border-radius:2px;margin-right:5px;vertical-align:-1px}
.legend{display:inline-block;margin:2px 10px 2px 0;font-size:12px}
#viewer{width:100%;max-width:960px;height:auto;background:#fff;border:1px solid #ddd;cursor:grab;display:block}
.controls{display:flex;flex-wrap:wrap;align-items:center;gap:10px;margin:6px 0;max-width:960px}
.controls input[type=range]{flex:1;min-width:200px}
.controls button{min-width:70px}
#viewer-label{font-variant-numeric:tabular-nums;font-size:13px;min-width:190px}
"""

_PAGE = """<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<meta name="generator" content="mocapskel">
<title>{title}</title>
<style>{css}</style>
</head>
<body>
<header><h1>{title}</h1><nav>{nav}</nav></header>
<main>
{body}
</main>
</body>
</html>
"""

_VIEWER_HTML = """<div class="controls">
<button type="button" id="viewer-play">Play</button>
<input type="range" id="viewer-slider" min="0" max="{n_max}" value="0" step="1" aria-label="frame">
<span id="viewer-label">frame 0</span>
</div>
<div class="controls">
<label><input type="checkbox" id="viewer-markers" checked> markers</label>
<label><input type="checkbox" id="viewer-skeleton" checked> skeleton</label>
<label><input type="checkbox" id="viewer-unc" checked> joint uncertainty (2 sd)</label>
<label><input type="checkbox" id="viewer-follow" checked> follow the subject</label>
<label>up axis <select id="viewer-up"><option value="z">Z</option><option value="y">Y</option></select></label>
<span class="note">drag to rotate, wheel to zoom, double-click to reset; space plays/pauses; {decim}</span>
</div>
<canvas id="viewer" width="960" height="600" aria-label="3-D view of the markers and the skeleton"></canvas>
<div>{legend}<span class="legend"><span class="chip" style="background:#222"></span>bones, joints (white)</span><span class="legend"><span class="chip" style="background:#ff7f0e"></span>joint's principal axes, ±2 sd</span><span class="legend"><span class="chip" style="background:#d62728"></span>… of a joint the prior sets</span></div>
<div id="viewer-status" data-ok="0" data-points="0" data-lines="0" data-unc="0" data-frame="-1" data-images="-1" data-error=""></div>
<noscript><p class="note">The 3-D view needs JavaScript.</p></noscript>
<script type="application/json" id="viewer-data">{data}</script>
<script>{script}</script>"""

_VIEWER_JS = r"""
(function () {
  "use strict";
  var status = document.getElementById("viewer-status");
  window.addEventListener("error", function (ev) {
    status.setAttribute("data-error", String((ev && ev.message) || "script error"));
  });
  window.addEventListener("load", function () {
    var imgs = document.querySelectorAll("img.plot"), ok = 0;
    for (var i = 0; i < imgs.length; i++) { if (imgs[i].complete && imgs[i].naturalWidth > 0) { ok++; } }
    status.setAttribute("data-images", ok + "/" + imgs.length);
  });
  var D = JSON.parse(document.getElementById("viewer-data").textContent);
  var canvas = document.getElementById("viewer");
  var ctx = canvas.getContext("2d");
  var slider = document.getElementById("viewer-slider");
  var playBtn = document.getElementById("viewer-play");
  var label = document.getElementById("viewer-label");
  var showMarkers = document.getElementById("viewer-markers");
  var showSkeleton = document.getElementById("viewer-skeleton");
  var upSelect = document.getElementById("viewer-up");
  var follow = document.getElementById("viewer-follow");
  var showUnc = document.getElementById("viewer-unc");
  var q = D.quantum_mm, n = D.n, S = D.names.length, M = D.labels.length;
  var view = { yaw: -0.7, pitch: 0.3, zoom: 1.0 };
  var frame = 0, playing = false, t0 = 0, f0 = 0;
  upSelect.value = D.up;

  // lab (x, y, z) -> (right, forward, up) for the chosen up axis
  function axes(x, y, z) { return upSelect.value === "y" ? [x, -z, y] : [x, y, z]; }

  // extent over all frames (lo, hi), each frame's centre (mean of its joints) and the
  // largest distance of anything drawn from its frame's centre (rad), in (right, forward, up)
  var lo, hi, centre, rad;
  function extent() {
    lo = [Infinity, Infinity, Infinity]; hi = [-Infinity, -Infinity, -Infinity];
    centre = []; rad = 0;
    var f, k, c, p, r;
    for (f = 0; f < n; f++) {
      var sum = [0, 0, 0], cnt = 0;
      r = D.joints[f];
      for (k = 0; k + 2 < r.length; k += 3) {
        if (r[k] === null || r[k + 1] === null || r[k + 2] === null) { continue; }
        p = axes(r[k] * q, r[k + 1] * q, r[k + 2] * q);
        sum[0] += p[0]; sum[1] += p[1]; sum[2] += p[2]; cnt++;
      }
      centre.push(cnt ? [sum[0] / cnt, sum[1] / cnt, sum[2] / cnt] : null);
    }
    var rows = [D.joints, D.markers, D.ends];
    for (var j = 0; j < rows.length; j++) {
      for (f = 0; f < n; f++) {
        r = rows[j][f];
        for (k = 0; k + 2 < r.length; k += 3) {
          if (r[k] === null || r[k + 1] === null || r[k + 2] === null) { continue; }
          p = axes(r[k] * q, r[k + 1] * q, r[k + 2] * q);
          for (c = 0; c < 3; c++) { if (p[c] < lo[c]) { lo[c] = p[c]; } if (p[c] > hi[c]) { hi[c] = p[c]; } }
          if (centre[f]) {
            var d = Math.sqrt(Math.pow(p[0] - centre[f][0], 2) + Math.pow(p[1] - centre[f][1], 2) + Math.pow(p[2] - centre[f][2], 2));
            if (d > rad) { rad = d; }
          }
        }
      }
    }
    for (c = 0; c < 3; c++) { if (!isFinite(lo[c])) { lo[c] = -500; hi[c] = 500; } }
    if (!(rad > 0)) { rad = 500; }
    // frames without joints keep the last known centre
    var last = [(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, (lo[2] + hi[2]) / 2];
    for (f = 0; f < n; f++) { if (centre[f]) { last = centre[f]; } else { centre[f] = last; } }
  }
  extent();

  // the point the view is centred on, and the radius that fits the canvas
  function focus() {
    if (follow.checked && n > 0) {
      return [[centre[frame][0], centre[frame][1], (lo[2] + hi[2]) / 2], Math.max(rad, (hi[2] - lo[2]) / 2)];
    }
    var r = 0.5 * Math.sqrt(Math.pow(hi[0] - lo[0], 2) + Math.pow(hi[1] - lo[1], 2) + Math.pow(hi[2] - lo[2], 2));
    return [[(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, (lo[2] + hi[2]) / 2], r || 1];
  }
  var F0 = [0, 0, 0], R0 = 1;
  function project(p, W, H) {
    var s = 0.48 * Math.min(W, H) / R0 * view.zoom;
    var a = p[0] - F0[0], b = p[1] - F0[1], h = p[2] - F0[2];
    var cyw = Math.cos(view.yaw), syw = Math.sin(view.yaw);
    var a2 = a * cyw - b * syw, b2 = a * syw + b * cyw;
    var cp = Math.cos(view.pitch), sp = Math.sin(view.pitch);
    var up = h * cp + b2 * sp;
    return [W / 2 + s * a2, H / 2 - s * up, b2 * cp - h * sp];
  }
  function point(rows, f, i) {
    var r = rows[f];
    if (!r || r[3 * i] === null || r[3 * i + 1] === null || r[3 * i + 2] === null) { return null; }
    return axes(r[3 * i] * q, r[3 * i + 1] * q, r[3 * i + 2] * q);
  }
  function niceStep(span) {
    var raw = span / 8, p = Math.pow(10, Math.floor(Math.log(raw) / Math.LN10)), m = raw / p;
    return (m < 2 ? 1 : m < 5 ? 2 : 5) * p;
  }
  function line(a, b) { ctx.beginPath(); ctx.moveTo(a[0], a[1]); ctx.lineTo(b[0], b[1]); ctx.stroke(); }
  function dot(p, r) { ctx.beginPath(); ctx.arc(p[0], p[1], r, 0, 2 * Math.PI); ctx.fill(); ctx.stroke(); }

  function draw() {
    var W = canvas.width, H = canvas.height, drawn = 0, lines = 0, i, p, a, b;
    ctx.clearRect(0, 0, W, H);
    ctx.fillStyle = "#ffffff"; ctx.fillRect(0, 0, W, H);
    var fr = focus(); F0 = fr[0]; R0 = fr[1];
    // floor grid (fixed in the lab, around the view's centre) at the lowest point of the take
    var ext = follow.checked ? [F0[0] - 1.3 * R0, F0[0] + 1.3 * R0, F0[1] - 1.3 * R0, F0[1] + 1.3 * R0] : [lo[0], hi[0], lo[1], hi[1]];
    var step = niceStep(Math.max(ext[1] - ext[0], ext[3] - ext[2], 1));
    var g0 = Math.floor(ext[0] / step) * step, g1 = Math.ceil(ext[1] / step) * step;
    var h0 = Math.floor(ext[2] / step) * step, h1 = Math.ceil(ext[3] / step) * step;
    ctx.strokeStyle = "#e4e4e4"; ctx.lineWidth = 1;
    for (var gx = g0; gx <= g1 + 1e-6; gx += step) { line(project([gx, h0, lo[2]], W, H), project([gx, h1, lo[2]], W, H)); }
    for (var gy = h0; gy <= h1 + 1e-6; gy += step) { line(project([g0, gy, lo[2]], W, H), project([g1, gy, lo[2]], W, H)); }
    // axes triad (lab x red, y green, z blue)
    var o = [g0, h0, lo[2]], L = step;
    var tri = [[[L, 0, 0], "#d62728"], [[0, L, 0], "#2ca02c"], [[0, 0, L], "#1f77b4"]];
    if (upSelect.value === "y") { tri = [[[L, 0, 0], "#d62728"], [[0, 0, L], "#2ca02c"], [[0, -L, 0], "#1f77b4"]]; }
    ctx.lineWidth = 2;
    for (i = 0; i < 3; i++) {
      ctx.strokeStyle = tri[i][1];
      line(project(o, W, H), project([o[0] + tri[i][0][0], o[1] + tri[i][0][1], o[2] + tri[i][0][2]], W, H));
    }
    if (showSkeleton.checked) {
      ctx.strokeStyle = "#222222"; ctx.lineWidth = 3.5; ctx.lineCap = "round";
      for (i = 0; i < S; i++) {
        if (D.parent[i] < 0) { continue; }
        a = point(D.joints, frame, D.parent[i]); b = point(D.joints, frame, i);
        if (a && b) { line(project(a, W, H), project(b, W, H)); lines++; }
      }
      for (i = 0; i < D.leaves.length; i++) {
        a = point(D.joints, frame, D.leaves[i]); b = point(D.ends, frame, i);
        if (a && b) { line(project(a, W, H), project(b, W, H)); lines++; }
      }
      ctx.fillStyle = "#ffffff"; ctx.lineWidth = 1.5;
      for (i = 0; i < S; i++) {
        p = point(D.joints, frame, i);
        if (p) { dot(project(p, W, H), 4.5); drawn++; }
      }
    }
    var uncLines = 0;
    if (showUnc.checked && D.unc && D.unc.joints.length) {
      ctx.lineWidth = 2; ctx.lineCap = "round";
      for (i = 0; i < D.unc.joints.length; i++) {
        p = point(D.joints, frame, D.unc.joints[i]);
        if (!p) { continue; }
        ctx.strokeStyle = D.unc.prior[i] ? "#d62728" : "#ff7f0e";
        for (var k = 0; k < 3; k++) {
          var v = point(D.unc.axes, frame, 3 * i + k);
          if (!v) { continue; }
          line(project([p[0] - v[0], p[1] - v[1], p[2] - v[2]], W, H), project([p[0] + v[0], p[1] + v[1], p[2] + v[2]], W, H));
          uncLines++;
        }
      }
    }
    status.setAttribute("data-unc", String(uncLines));
    if (showMarkers.checked) {
      ctx.lineWidth = 0.8; ctx.strokeStyle = "#333333";
      for (i = 0; i < M; i++) {
        p = point(D.markers, frame, i);
        if (!p) { continue; }
        var s = D.marker_segment[i];
        ctx.fillStyle = s >= 0 ? D.colours[s] : "#9a9a9a";
        dot(project(p, W, H), 3.5); drawn++;
      }
    }
    var take = frame * D.step;
    label.textContent = "frame " + take + " / " + D.frames + (D.rate > 0 ? "  \u00b7  " + (take / D.rate).toFixed(2) + " s" : "");
    status.setAttribute("data-points", String(drawn));
    status.setAttribute("data-lines", String(lines));
    status.setAttribute("data-frame", String(take));
  }

  function setFrame(f) { frame = Math.max(0, Math.min(n - 1, f)); slider.value = String(frame); draw(); }
  function tick(now) {
    if (!playing) { return; }
    var per = D.rate > 0 ? D.rate / D.step : 30;
    var f = f0 + Math.floor((now - t0) / 1000 * per);
    setFrame(n > 0 ? f % n : 0);
    window.setTimeout(function () { tick(performance.now()); }, 1000 / 60);  // timers also run headless
  }
  function toggle() {
    playing = !playing;
    playBtn.textContent = playing ? "Pause" : "Play";
    if (playing) { t0 = performance.now(); f0 = frame; tick(t0); }
  }
  playBtn.addEventListener("click", toggle);
  slider.addEventListener("input", function () { if (playing) { toggle(); } setFrame(parseInt(slider.value, 10) || 0); });
  showMarkers.addEventListener("change", draw);
  showSkeleton.addEventListener("change", draw);
  follow.addEventListener("change", draw);
  showUnc.addEventListener("change", draw);
  upSelect.addEventListener("change", function () { extent(); draw(); });
  document.addEventListener("keydown", function (ev) {
    if (ev.code === "Space" && ev.target === document.body) { ev.preventDefault(); toggle(); }
  });
  var drag = null;
  canvas.addEventListener("mousedown", function (ev) { drag = [ev.clientX, ev.clientY, view.yaw, view.pitch]; canvas.style.cursor = "grabbing"; });
  window.addEventListener("mouseup", function () { drag = null; canvas.style.cursor = "grab"; });
  window.addEventListener("mousemove", function (ev) {
    if (!drag) { return; }
    view.yaw = drag[2] + (ev.clientX - drag[0]) * 0.01;
    view.pitch = Math.max(-1.55, Math.min(1.55, drag[3] + (ev.clientY - drag[1]) * 0.01));
    draw();
  });
  canvas.addEventListener("wheel", function (ev) {
    ev.preventDefault();
    view.zoom = Math.max(0.2, Math.min(20, view.zoom * Math.exp(-ev.deltaY * 0.001)));
    draw();
  }, { passive: false });
  canvas.addEventListener("dblclick", function () { view.yaw = -0.7; view.pitch = 0.3; view.zoom = 1.0; draw(); });

  setFrame(0);
  status.setAttribute("data-ok", "1");
})();
"""
