"""The status page: one self-contained HTML text (inline CSS and JavaScript, no CDN).

It loads ``/api/history`` (the last minute) and ``/api/axes``, then follows
``/api/stream`` (one event per sample); a closed stream is reopened by the
browser (EventSource). One row per axis; the "plot" box of a row puts its
position and velocity on the two canvases (the last 60 s). The page only reads:
it has no form, no button that sends anything, and the server answers GET only.
Each value cell has an id (``pos-<addr>``, ``vel-<addr>``, ``state-<addr>`` ...)
for tests. ``<link rel=icon href="data:,">`` keeps the browser from asking
for a favicon (a 404 would be a console error). Pure: a string.
"""
from __future__ import annotations

from typing import Final

PAGE: Final = """<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<link rel="icon" href="data:,">
<title>tcp-bridge status</title>
<style>
body{font:14px system-ui,sans-serif;margin:1em;color:#222;background:#fafafa}
h1{font-size:1.3em;margin:0 0 .3em}
#meta{color:#666;margin-bottom:.6em}
table{border-collapse:collapse;background:#fff}
th,td{border:1px solid #ccc;padding:3px 7px;text-align:left;white-space:nowrap}
th{background:#eee}
td.num{text-align:right;font-variant-numeric:tabular-nums}
.bad{color:#b00}.ok{color:#070}.stale{color:#999}
canvas{background:#fff;border:1px solid #ccc;margin-top:.6em;display:block}
</style></head>
<body>
<h1>tcp-bridge: axes</h1>
<div id="meta">waiting for the first sample&hellip;</div>
<table><thead><tr><th>plot</th><th>axis</th><th>bus/node</th><th>state</th><th>mode</th>
<th>position</th><th>velocity</th><th>target reached</th><th>error bits</th><th>R86</th>
<th>last error</th></tr></thead><tbody id="rows"></tbody></table>
<canvas id="pos" width="900" height="200"></canvas>
<canvas id="vel" width="900" height="200"></canvas>
<p><a id="history-csv" href="/api/history.csv" download>the last minute as CSV</a></p>
<script>
"use strict";
const COLORS = ["#1f77b4","#d62728","#2ca02c","#ff7f0e","#9467bd","#8c564b","#e377c2","#17becf"];
const WINDOW = 60;  // seconds shown on the plots
let hist = [];      // {t, p: {addr: position}, v: {addr: velocity}}
let plotted = null; // addresses ticked; null until the first sample (then: all)
let order = [];

function text(v, digits) {
  if (v === null || v === undefined) return "";
  return digits === undefined ? String(v) : Number(v).toFixed(digits);
}
function cell(tr, id, cls) {
  const td = document.createElement("td"); td.id = id; if (cls) td.className = cls;
  tr.appendChild(td); return td;
}
function ensureRow(a) {
  const id = "axis-" + a.addr;
  let tr = document.getElementById(id);
  if (tr) return tr;
  tr = document.createElement("tr"); tr.id = id;
  const box = document.createElement("input"); box.type = "checkbox"; box.id = "plot-" + a.addr;
  box.checked = plotted.has(a.addr);
  box.addEventListener("change", () => {
    if (box.checked) plotted.add(a.addr); else plotted.delete(a.addr); draw();
  });
  const td = document.createElement("td"); td.appendChild(box); tr.appendChild(td);
  for (const [key, cls] of [["addr"],["bus"],["state"],["mode"],["pos","num"],["vel","num"],
                            ["reached"],["errors"],["ack","num"],["last"]]) {
    cell(tr, key + "-" + a.addr, cls);
  }
  document.getElementById("rows").appendChild(tr);
  return tr;
}
function show(sample) {
  if (plotted === null) plotted = new Set(sample.axes.map(a => a.addr));
  order = sample.axes.map(a => a.addr);
  for (const a of sample.axes) {
    ensureRow(a);
    const set = (key, v, cls) => {
      const td = document.getElementById(key + "-" + a.addr);
      td.textContent = v; if (cls !== undefined) td.className = cls;
    };
    set("addr", a.addr);
    set("bus", a.bus + "/" + a.node);
    set("state", a.has_drive ? text(a.state) : "no drive",
        a.state === "fault" ? "bad" : a.state === "operation enabled" ? "ok" : "");
    set("mode", text(a.mode_name));
    set("pos", text(a.position, 3), "num");
    set("vel", text(a.velocity, 3), "num");
    set("reached", a.target_reached === null ? "" : (a.target_reached ? "yes" : "no"));
    set("errors", a.errors === null ? "" : (a.errors.length ? a.errors.join(", ") : "none"),
        a.errors && a.errors.length ? "bad" : "");
    set("ack", text(a.moving_ack), "num");
    const le = a.last_error;
    set("last", le ? new Date(le.t * 1000).toLocaleTimeString() + " R" + le.cmd + ": " + le.error
                   : "", le ? "bad" : "");
  }
  document.getElementById("meta").textContent = "sample " + sample.seq + " at " +
    new Date(sample.t * 1000).toLocaleTimeString() + ", every " + sample.period + " s";
}
function remember(sample) {
  if (hist.length && sample.t <= hist[hist.length - 1].t) return;  // already known
  const p = {}, v = {};
  for (const a of sample.axes) { p[a.addr] = a.position; v[a.addr] = a.velocity; }
  hist.push({t: sample.t, p: p, v: v});
  const cut = sample.t - WINDOW;
  while (hist.length && hist[0].t < cut) hist.shift();
}
function plot(id, key, label) {
  const c = document.getElementById(id), g = c.getContext("2d");
  g.clearRect(0, 0, c.width, c.height);
  if (!hist.length || plotted === null) return;
  const now = hist[hist.length - 1].t, left = 60, w = c.width - left - 10, h = c.height - 40;
  let lo = Infinity, hi = -Infinity;
  for (const s of hist) for (const a of plotted) {
    const y = s[key][a]; if (y !== null && y !== undefined) { lo = Math.min(lo, y); hi = Math.max(hi, y); }
  }
  if (lo === Infinity) { lo = -1; hi = 1; }
  if (hi - lo < 1e-9) { lo -= 1; hi += 1; }
  g.fillStyle = "#222"; g.font = "12px sans-serif";
  g.fillText(label + " (last " + WINDOW + " s)", left, 14);
  g.fillText(hi.toPrecision(5), 2, 24); g.fillText(lo.toPrecision(5), 2, 20 + h);
  g.strokeStyle = "#ddd"; g.strokeRect(left, 20, w, h);
  order.forEach((addr, i) => {
    if (!plotted.has(addr)) return;
    g.strokeStyle = COLORS[i % COLORS.length]; g.beginPath();
    let pen = false;
    for (const s of hist) {
      const y = s[key][addr];
      if (y === null || y === undefined) { pen = false; continue; }
      const px = left + w * (1 - (now - s.t) / WINDOW), py = 20 + h * (1 - (y - lo) / (hi - lo));
      if (pen) g.lineTo(px, py); else g.moveTo(px, py);
      pen = true;
    }
    g.stroke();
    g.fillStyle = g.strokeStyle; g.fillText("axis " + addr, left + 8 + 60 * i, c.height - 4);
  });
}
function draw() { plot("pos", "p", "position"); plot("vel", "v", "velocity"); }
function take(sample) { if (!sample.axes) return; show(sample); remember(sample); draw(); }

async function start() {
  const history = await (await fetch("/api/history")).json();
  for (const s of history.samples) {
    const p = {}, v = {};
    history.axes.forEach((addr, i) => { p[addr] = s.position[i]; v[addr] = s.velocity[i]; });
    hist.push({t: s.t, p: p, v: v});
  }
  const latest = await (await fetch("/api/axes")).json();
  if (latest.axes && latest.axes.length) { show(latest); draw(); }
  const stream = new EventSource("/api/stream");
  stream.onmessage = (e) => take(JSON.parse(e.data));
}
start();
</script>
</body></html>
"""
