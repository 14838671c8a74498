"""The HTML plot of a recording: one self-contained file drawn by uPlot in the browser.

The layout is :func:`epos_link.tools.plot.panels`'s (one chart per quantity, the
CiA 402 state as a thin band last); this module only puts it on a page:

* uPlot (:mod:`epos_link.vendor`, MIT, inlined with its licence notice) draws each
  chart; the recording is inlined as JSON (``<script type="application/json"
  id="plot-data">``: ``xs``, the ``panels`` with their ``series``, ``trigger``,
  ``gaps``), a missing value being ``null``, which uPlot leaves as a gap.
* **Cursor**: moving over any chart moves a cursor on all of them (uPlot's cursor
  sync); the legend under each chart shows the time and each trace's value at
  the sample under the cursor, the band's legend the state's name.
* **Zoom**: drag across a chart to zoom the time axis of all; double-click to
  show everything again.
* **Marks**: the trigger (a dashed line labelled "trigger", ``div.trigger``) and
  the gaps (grey spans, ``div.gap``) are elements laid over each chart's plotting
  area, moved with the zoom: a test (or a person's inspector) finds them in the page.

Pure: returns a string. Nothing is loaded from the network: no ``src=`` or
``href=`` to anything (tests/test_record_plot.py checks it).
"""
from __future__ import annotations

import html
import json
import math
from typing import Any, Optional, Sequence

from ..vendor import UPLOT_VERSION, inline_script, uplot_css, uplot_js
from .plot import STATE_COLOURS, Panel, gap_spans

COLOURS = ("#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b")
WIDTH, HEIGHT, BAND_HEIGHT = 1000, 230, 64


def _json_value(v: float) -> Optional[float]:
    return None if math.isnan(v) else v


def plot_data(found: Sequence[Panel], title: str, trigger: Optional[float]) -> dict[str, Any]:
    """What the page's script draws (JSON-ready; NaN becomes null)."""
    xs: list[float] = []
    for panel in found:
        for trace in panel.traces:
            xs = list(trace.xs)
            break
        if xs:
            break
    panels = []
    for panel in found:
        series = [{"label": t.label, "ys": [_json_value(y) for y in t.ys],
                   "colour": COLOURS[k % len(COLOURS)]} for k, t in enumerate(panel.traces)]
        panels.append({"ylabel": panel.ylabel, "unit": panel.unit, "band": panel.band,
                       "states": {str(int(v)): name for v, name in panel.ticks or ()},
                       "series": series})
    return {"title": title, "xs": xs, "panels": panels, "trigger": trigger,
            "gaps": [list(g) for g in gap_spans(found)],
            "state_colours": {str(k): v for k, v in STATE_COLOURS.items()}}


_STYLE = """
body{font:13px system-ui,sans-serif;margin:12px;color:#222}
h3{margin:0 0 4px;font-size:15px}
p.help{margin:0 0 8px;color:#666}
.chart{margin-bottom:6px}
.u-legend{font-size:12px;text-align:left}
.u-legend .u-value{font-variant-numeric:tabular-nums;min-width:7em;display:inline-block}
div.trigger{position:absolute;top:0;bottom:0;width:0;border-left:1.5px dashed #333;
 pointer-events:none}
div.trigger span{position:absolute;top:0;left:3px;font-size:11px;color:#333;
 background:rgba(255,255,255,.8)}
div.gap{position:absolute;top:0;bottom:0;background:rgba(150,150,150,.18);pointer-events:none}
"""

# The page's own script: builds one uPlot per panel from #plot-data.
_SCRIPT = r"""
"use strict";
const D = JSON.parse(document.getElementById("plot-data").textContent);
const charts = [];
let syncing = false;
function fmt(v) {
  if (v === null || v === undefined) return "\u2013";
  const a = Math.abs(v);
  return a !== 0 && (a >= 1e6 || a < 1e-3) ? v.toExponential(4) : +v.toPrecision(7) + "";
}
function marks(u) {  // the trigger line and the gaps, laid over the plotting area
  for (const el of u.over.querySelectorAll(".mark")) el.remove();
  const add = (cls, left, width, text) => {
    const el = document.createElement("div");
    el.className = cls + " mark"; el.style.left = left + "px";
    if (width !== null) el.style.width = width + "px";
    if (text) { const s = document.createElement("span"); s.textContent = text; el.appendChild(s); }
    u.over.appendChild(el); return el;
  };
  const w = u.over.clientWidth;
  for (const [a, b] of D.gaps) {
    const l = Math.max(u.valToPos(a, "x"), 0), r = Math.min(u.valToPos(b, "x"), w);
    if (r > l) { const g = add("gap", l, r - l, ""); g.dataset.start = a; g.dataset.end = b; }
  }
  if (D.trigger !== null) {
    const x = u.valToPos(D.trigger, "x");
    if (x >= 0 && x <= w) add("trigger", x, null, u === charts[0] ? "trigger" : "");
  }
}
function alone(ys) {
  const out = [];
  for (let k = 0; k < ys.length; k++)
    if (ys[k] !== null && (k === 0 || ys[k - 1] === null) && (k === ys.length - 1 || ys[k + 1] === null)
        && ys.length > 1) out.push(k);
  return out;
}
function band(u, states) {  // the state strip: coloured spans, named where they fit
  const ys = u.data[1], xs = u.data[0], ctx = u.ctx, top = u.bbox.top, h = u.bbox.height;
  ctx.save();
  ctx.font = (11 * devicePixelRatio) + "px system-ui,sans-serif";
  ctx.textAlign = "center"; ctx.textBaseline = "middle";
  let k = 0;
  while (k < xs.length - 1) {
    if (ys[k] === null) { k++; continue; }
    let j = k;
    while (j + 1 < xs.length - 1 && ys[j + 1] === ys[k]) j++;
    const end = ys[j + 1] === null ? xs[j] : xs[j + 1];
    const x0 = u.valToPos(xs[k], "x", true), x1 = u.valToPos(end, "x", true);
    ctx.fillStyle = D.state_colours[String(ys[k])] || "#bbb";
    ctx.fillRect(x0, top, Math.max(x1 - x0, 1), h);
    const name = states[String(ys[k])] || "";
    if (x1 - x0 > ctx.measureText(name).width + 8) {
      ctx.fillStyle = "#111"; ctx.fillText(name, (x0 + x1) / 2, top + h / 2);
    }
    k = j + 1;
  }
  ctx.restore();
}
function build(panel, index) {
  const el = document.createElement("div"); el.className = "chart"; el.id = "chart-" + index;
  document.getElementById("charts").appendChild(el);
  const series = [{label: "time [s]", value: (u, v) => v === null ? "\u2013" : fmt(v)}];
  const data = [D.xs];
  for (const s of panel.series) {
    data.push(s.ys);
    series.push(panel.band
      ? {label: "state", paths: () => null, points: {show: false},
         value: (u, v) => v === null ? "\u2013" : (panel.states[String(v)] || String(v))}
      : {label: s.label + (panel.unit ? " [" + panel.unit + "]" : ""), stroke: s.colour,
         width: 1.5, value: (u, v) => fmt(v),
         // A sample alone between two gaps has no line to it: a dot.
         points: {show: true, size: 5, fill: s.colour, filter: () => alone(s.ys)}});
  }
  const opts = {
    width: Math.max(Math.min(window.innerWidth - 40, %(width)d), 400),
    // The last chart also carries the time axis' ticks and label (about 50 px).
    height: (panel.band ? %(band)d : %(height)d) + (index === D.panels.length - 1 ? 50 : 0),
    scales: {x: {time: false}, y: panel.band ? {range: [0, 1]} : {}},
    axes: [index === D.panels.length - 1 ?
           {label: D.trigger === null ? "time [s] (not triggered)" : "time from trigger [s]"} :
           {size: 22, label: ""},
           panel.band ? {size: 80, ticks: {show: false}, grid: {show: false}, values: () => [],
                         label: "state"}
                      : {label: panel.unit ? "[" + panel.unit + "]" : panel.ylabel, size: 80}],
    series: series,
    cursor: {sync: {key: "recording"}, drag: {x: true, y: false}},
    legend: {live: true},
    hooks: {
      draw: [u => { if (panel.band) band(u, panel.states); marks(u); }],
      setScale: [(u, key) => {
        if (key !== "x" || syncing) return;
        syncing = true;
        for (const o of charts) if (o !== u) o.setScale("x", {min: u.scales.x.min, max: u.scales.x.max});
        syncing = false;
      }],
    },
  };
  const u = new uPlot(opts, data, el);
  u.root.dataset.ylabel = panel.ylabel;
  charts.push(u);
}
D.panels.forEach(build);
window.plotCharts = charts;  // for tests and for a person's console
"""


def html_page(found: Sequence[Panel], title: str, *, trigger: Optional[float] = 0.0) -> str:
    # "<" only occurs inside JSON strings, where \u003c means the same: no "</script>".
    data = json.dumps(plot_data(found, title, trigger), allow_nan=False).replace("<", "\\u003c")
    script = _SCRIPT % {"width": WIDTH, "height": HEIGHT, "band": BAND_HEIGHT}
    holes = len(gap_spans(found))
    notes = [] if trigger is not None else ["not triggered: time 0 is the last sample"]
    if holes:
        notes.append(f"{holes} gap{'s' if holes != 1 else ''} where samples are missing (grey)")
    return ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            f"<title>{html.escape(title)}</title>\n"
            f"<style>{uplot_css()}</style><style>{_STYLE}</style></head><body>\n"
            f"<h3>{html.escape(title)}</h3>\n<p class=\"help\">"
            + html.escape("; ".join(notes + ["the legends show the values at the cursor",
                                             "drag across a chart to zoom, double-click to "
                                             "show all"]))
            + "</p>\n<div id=\"charts\"></div>\n"
            f"<script type=\"application/json\" id=\"plot-data\">{data}</script>\n"
            f"<!-- uPlot {UPLOT_VERSION}, MIT licence (c) Leon Sorokin: "
            "epos_link/vendor/uplot/LICENSE -->\n"
            f"<script>{inline_script(uplot_js())}</script>\n"
            f"<script>{inline_script(script)}</script>\n</body></html>\n")

__all__ = ["html_page", "plot_data"]
