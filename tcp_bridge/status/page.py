"""The status page: one self-contained HTML text (inline CSS and JavaScript, no CDN).

It loads ``/api/history`` (the last minute) and ``/api/axes``, then follows
``/api/stream`` (one event per sample); a closed stream is reopened by the
browser (EventSource). The page only reads: it has no form, no button that
sends anything, and the server answers GET only. ``<link rel=icon href="data:,">``
keeps the browser from asking for a favicon (a 404 would be a console error).

What a person reads (issue 34 item 4, "a status page that says why"):

* one row per axis, columns named in words (``move started (R86)``, not ``R86``),
  with their units: positions in the axis's user units (``position_factor``),
  velocities in user units per second;
* the **state cell** says what is wrong, coloured, with the reason under it,
  wrapped so that it is visible at 1280 px (``condition`` of
  :mod:`tcp_bridge.status.rows`: no bus, bus silent, silent, error, fault), and
  said once; ``last error`` (time, command) repeats a reason only when the state
  cell does not already show it, and is empty again once the command answers;
* "target reached" only in operation enabled (empty for a disabled axis);
* times in 24-hour form, ``HH:MM:SS`` in the browser's time zone, whatever its
  locale;
* the last minute of the ticked axes' positions and velocities, drawn by uPlot
  (:mod:`epos_link.vendor`, MIT, inlined): time ticks, labelled axes with units,
  a cursor whose values show in the legend under each chart (no legend on the data),
  gaps where an axis gave no value; under them, a link to the same minute as CSV
  (``/api/history.csv``, :mod:`tcp_bridge.status.history_csv`).

Each value cell has an id (``pos-<addr>``, ``vel-<addr>``, ``state-<addr>`` ...) and
the state cell a ``data-kind``, for tests. Pure: a string.
"""
from __future__ import annotations

from typing import Final

from epos_link.vendor import inline_script, uplot_css, uplot_js

_STYLE = """
body{font:14px system-ui,sans-serif;margin:1em;color:#222;background:#fafafa}
h1{font-size:1.3em;margin:0 0 .3em}
#meta{color:#666;margin-bottom:.6em}
table{border-collapse:collapse;background:#fff}
th,td{border:1px solid #ccc;padding:3px 7px;text-align:left;white-space:nowrap;vertical-align:top}
th{background:#eee;font-weight:600}
th small{font-weight:normal;color:#555}
td.num{text-align:right;font-variant-numeric:tabular-nums}
td.state{white-space:normal;min-width:11em;max-width:26em}
td.state .why{font-size:12px;margin-top:2px;overflow-wrap:anywhere}
td.last{white-space:normal;max-width:16em;font-size:12px;overflow-wrap:anywhere}
td.kind-ok{color:#222}
td.kind-enabled{color:#070}
td.kind-fault,td.kind-no-bus,td.kind-bus-silent{background:#fde0dd;color:#8b0000;font-weight:600}
td.kind-silent,td.kind-error{background:#fff1c9;color:#7a4a00;font-weight:600}
td .why{font-weight:normal}
.bad{color:#b00}
.chart{background:#fff;border:1px solid #ccc;margin-top:.6em;display:inline-block;padding:4px}
.u-legend{font-size:12px;text-align:left}
.u-legend .u-value{font-variant-numeric:tabular-nums}
"""

_SCRIPT = r"""
"use strict";
const WINDOW = 60;  // seconds shown on the charts
const COLORS = ["#1f77b4","#d62728","#2ca02c","#ff7f0e","#9467bd","#8c564b","#e377c2","#17becf"];
let order = [];      // axis addresses, in the order of the samples
let times = [], pos = {}, vel = {};  // the charts' data: times, and per axis its values
let charts = null;
let hidden = new Set();  // axes unticked by the person

function two(n) { return (n < 10 ? "0" : "") + n; }
function hms(t) {  // 24-hour time in the browser's zone, whatever its locale
  const d = new Date(t * 1000);
  return two(d.getHours()) + ":" + two(d.getMinutes()) + ":" + two(d.getSeconds());
}
function num(v, digits) {
  return v === null || v === undefined ? "" : Number(v).toFixed(digits);
}
function ensureRow(a) {
  const id = "axis-" + a.addr;
  let tr = document.getElementById(id);
  if (tr) return tr;
  tr = document.createElement("tr"); tr.id = id;
  const cells = [["addr"], ["bus"], ["state", "state"], ["mode"], ["pos", "num"], ["vel", "num"],
                 ["reached"], ["errors"], ["ack", "num"], ["last", "last"]];
  for (const [key, cls] of cells) {
    const td = document.createElement("td"); td.id = key + "-" + a.addr;
    if (cls) td.className = cls;
    tr.appendChild(td);
  }
  const box = document.createElement("input"); box.type = "checkbox"; box.id = "plot-" + a.addr;
  box.checked = !hidden.has(a.addr); box.title = "on the charts";
  box.addEventListener("change", () => {
    if (box.checked) hidden.delete(a.addr); else hidden.add(a.addr);
    showSeries();
  });
  const addr = tr.firstChild; addr.appendChild(box); addr.appendChild(document.createTextNode(""));
  document.getElementById("rows").appendChild(tr);
  return tr;
}
function setText(key, a, text, cls) {
  const td = document.getElementById(key + "-" + a.addr);
  td.textContent = text;
  if (cls !== undefined) td.className = cls;
  return td;
}
function showState(a) {
  const td = document.getElementById("state-" + a.addr);
  const c = a.condition || {kind: "ok", text: a.state || "", reason: ""};
  const kind = c.kind === "ok" && a.state === "operation enabled" ? "enabled" : c.kind;
  td.className = "state kind-" + kind.replace(/ /g, "-");
  td.dataset.kind = c.kind;
  td.textContent = c.text;
  if (c.reason) {
    const why = document.createElement("div"); why.className = "why"; why.textContent = c.reason;
    td.appendChild(why);
  }
  return c;
}
function show(sample) {
  order = sample.axes.map(a => a.addr);
  for (const a of sample.axes) {
    ensureRow(a);
    const addrCell = document.getElementById("addr-" + a.addr);
    addrCell.lastChild.textContent = " " + a.addr;
    setText("bus", a, a.bus + " / " + a.node);
    const c = showState(a);
    setText("mode", a, a.mode_name || "");
    setText("pos", a, num(a.position, 3), "num");
    setText("vel", a, num(a.velocity, 3), "num");
    setText("reached", a, a.target_reached === null ? "" : (a.target_reached ? "yes" : "no"));
    setText("errors", a, a.errors === null ? "" : (a.errors.length ? a.errors.join(", ") : "none"),
            a.errors && a.errors.length ? "bad" : "");
    setText("ack", a, a.moving_ack === null ? "" : (a.moving_ack ? "yes" : "no"), "num");
    const le = a.last_error;
    let last = "";
    if (le) {
      last = hms(le.t) + " R" + two(le.cmd);
      if (!c.reason || c.reason.indexOf(le.error) < 0) last += ": " + le.error;  // said once
    }
    setText("last", a, last, "last" + (le ? " bad" : ""));
  }
  document.getElementById("meta").textContent = "sample " + sample.seq + " at " +
    hms(sample.t) + ", every " + sample.period + " s; positions in user units, " +
    "velocities in user units/s";
}
function remember(t, p, v) {
  if (times.length && t <= times[times.length - 1]) return;  // already known
  times.push(t);
  for (const addr of order) {
    (pos[addr] = pos[addr] || new Array(times.length - 1).fill(null)).push(p[addr] ?? null);
    (vel[addr] = vel[addr] || new Array(times.length - 1).fill(null)).push(v[addr] ?? null);
  }
  while (times.length && times[0] < t - WINDOW) {
    times.shift();
    for (const addr of order) { pos[addr].shift(); vel[addr].shift(); }
  }
}
function chart(id, what, unit) {
  const series = [{label: "time", value: (u, t) => t === null ? "\u2013" : hms(t)}];
  order.forEach((addr, i) => series.push({
    label: "axis " + addr, stroke: COLORS[i % COLORS.length], width: 1.5, show: !hidden.has(addr),
    value: (u, v) => v === null || v === undefined ? "\u2013" : Number(v).toFixed(3)}));
  const opts = {
    width: Math.max(Math.min(window.innerWidth - 60, 1180), 400), height: 200,
    title: what + " (last " + WINDOW + " s)",
    scales: {x: {time: true}},
    // Whole seconds apart at least: labels in HH:MM:SS are then never repeated.
    axes: [{values: (u, splits) => splits.map(hms), label: "time",
            incrs: [1, 2, 5, 10, 15, 30, 60, 120, 300, 600, 900, 1800, 3600]},
           {label: what + " [" + unit + "]", size: 80}],
    series: series,
    cursor: {sync: {key: "status"}, drag: {x: false, y: false}},
    legend: {live: true},
  };
  return new uPlot(opts, [[]].concat(order.map(() => [])), document.getElementById(id));
}
function draw() {
  if (!order.length) return;
  if (charts === null)
    charts = [chart("pos", "position", "user units"), chart("vel", "velocity", "user units/s")];
  charts[0].setData([times].concat(order.map(a => pos[a] || [])));
  charts[1].setData([times].concat(order.map(a => vel[a] || [])));
}
function showSeries() {
  if (charts === null) return;
  order.forEach((addr, i) => { for (const u of charts) u.setSeries(i + 1, {show: !hidden.has(addr)}); });
}
function take(sample) {
  if (!sample.axes) return;
  show(sample);
  const p = {}, v = {};
  for (const a of sample.axes) { p[a.addr] = a.position; v[a.addr] = a.velocity; }
  remember(sample.t, p, v); draw();
}
async function start() {
  const history = await (await fetch("/api/history")).json();
  order = history.axes;
  for (const s of history.samples) {
    const p = {}, v = {};
    history.axes.forEach((addr, i) => { p[addr] = s.position[i]; v[addr] = s.velocity[i]; });
    remember(s.t, p, v);
  }
  const latest = await (await fetch("/api/axes")).json();
  if (latest.axes && latest.axes.length) take(latest);
  const stream = new EventSource("/api/stream");
  stream.onmessage = (e) => take(JSON.parse(e.data));
}
window.statusCharts = () => charts;  // for tests and for a person's console
start();
"""

PAGE: Final = f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<link rel="icon" href="data:,">
<title>tcp-bridge status</title>
<style>{uplot_css()}</style>
<style>{_STYLE}</style></head>
<body>
<h1>tcp-bridge: axes</h1>
<div id="meta">waiting for the first sample&hellip;</div>
<table><thead><tr><th>axis</th><th>bus / node</th><th>state</th><th>mode</th>
<th>position <small>[user units]</small></th><th>velocity <small>[user units/s]</small></th>
<th>target reached</th><th>error bits <small>(R11)</small></th>
<th>move started <small>(R86)</small></th><th>last error</th></tr></thead>
<tbody id="rows"></tbody></table>
<div><div class="chart" id="pos"></div></div>
<div><div class="chart" id="vel"></div></div>
<p><a id="history-csv" href="/api/history.csv" download>the last minute as CSV</a></p>
<!-- uPlot, MIT licence (c) Leon Sorokin: epos_link/vendor/uplot/LICENSE -->
<script>{inline_script(uplot_js())}</script>
<script>{inline_script(_SCRIPT)}</script>
</body></html>
"""
