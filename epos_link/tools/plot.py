"""Plots of a recording: PNG or SVG through matplotlib, or one self-contained HTML file.

The layout is decided once, here, for both (:func:`panels`): one axis per
physical quantity (the objects that share a unit share an axis; an object
without a unit has its own), all over the same time axis, and the statusword
as a step trace of its CiA 402 state (CiA 402-2 6.4.1.4), labelled with the
state names. Values that are not numbers (strings, bytes) are not drawn.

* PNG/SVG: matplotlib, an optional dependency (``pip install 'epos-link[plot]'``);
  without it :class:`PlotUnavailable` says so. Each line carries its object's
  name as its gid, so an SVG names its traces (``<g id="...">``).
* HTML: no script or style from the network. Each axis is an inline SVG whose
  traces are polylines in data coordinates inside a nested ``<svg viewBox>``;
  a few lines of inline JavaScript zoom the time axis of all of them at once
  (drag across an axis; double-click to show everything again) by changing the
  viewBox, and redraw the time ticks.
"""
from __future__ import annotations

import html
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional, Sequence

from ..cia402 import State, state_text
from ..errors import LocalProtocolError
from .recording import Channel, Value, state_of

FORMATS = (".png", ".svg", ".html", ".htm")
STATE_AXIS = "CiA 402 state"
NO_STATE = -1  # a statusword that codes no state


class PlotUnavailable(LocalProtocolError):
    """matplotlib is not installed, or the file name asks for a format we do not draw."""


@dataclass(frozen=True)
class Trace:
    label: str
    xs: tuple[float, ...]
    ys: tuple[float, ...]
    step: bool = False


@dataclass(frozen=True)
class Panel:
    ylabel: str
    traces: tuple[Trace, ...]
    ticks: Optional[tuple[tuple[float, str], ...]] = None  # fixed y ticks (the state axis)


def _number(value: Value) -> Optional[float]:
    if isinstance(value, bool):
        return float(value)
    if isinstance(value, (int, float)) and math.isfinite(value):
        return float(value)
    return None


def panels(channels: Sequence[Channel], rows: Sequence[tuple[float, Sequence[Value]]]) -> list[Panel]:
    """The axes of a plot, in the order their objects were named."""
    xs = tuple(t for t, _ in rows)
    order: list[str] = []
    groups: dict[str, list[Trace]] = {}
    state_trace: Optional[Trace] = None
    seen_states: set[int] = set()
    for i, ch in enumerate(channels):
        if ch.is_statusword:
            states = [state_of(v[i]) for _, v in rows]
            ys = tuple(float(NO_STATE if s is None else int(s)) for s in states)
            seen_states.update(int(y) for y in ys)
            state_trace = Trace(f"{ch.name} state", xs, ys, step=True)
            order.append(STATE_AXIS)
            continue
        numbers = [_number(v[i]) for _, v in rows]
        if not rows or any(n is None for n in numbers):
            continue
        key = f"[{ch.unit}]" if ch.unit else ch.name  # an axis per unit, else per object
        if key not in groups:
            groups[key] = []
            order.append(key)
        groups[key].append(Trace(ch.name, xs, tuple(n for n in numbers if n is not None)))
    out = []
    for key in order:
        if key == STATE_AXIS and state_trace is not None:
            ticks = [(float(s), state_text(State(s))) for s in sorted(int(x) for x in State)]
            if NO_STATE in seen_states:
                ticks.insert(0, (float(NO_STATE), state_text(None)))
            out.append(Panel(STATE_AXIS, (state_trace,), tuple(ticks)))
        elif key in groups:
            traces = tuple(groups[key])
            one = len(traces) == 1 and key.startswith("[")  # "position actual value [inc]"
            out.append(Panel(f"{traces[0].label} {key}" if one else key, traces))
    return out


def write_plot(path: str, found: Sequence[Panel], title: str) -> None:
    suffix = Path(path).suffix.lower()
    if suffix in (".html", ".htm"):
        Path(path).write_text(html_page(found, title), encoding="utf-8")
    elif suffix in (".png", ".svg"):
        figure(found, title).savefig(path, dpi=80)
    else:
        raise PlotUnavailable(f"{path}: a plot is .png, .svg or .html")


def figure(found: Sequence[Panel], title: str) -> Any:
    """A matplotlib Figure (no pyplot, so no global state and no display needed)."""
    try:
        from matplotlib.figure import Figure
    except ImportError:
        raise PlotUnavailable("PNG and SVG plots need matplotlib: pip install 'epos-link[plot]' "
                              "(or pip install matplotlib); an .html plot needs nothing") from None
    fig = Figure(figsize=(8.0, 1.0 + 2.0 * max(len(found), 1)), layout="constrained")
    axes = fig.subplots(max(len(found), 1), 1, sharex=True, squeeze=False)[:, 0]
    for ax, panel in zip(axes, found):
        for trace in panel.traces:
            if trace.step:
                (line,) = ax.step(trace.xs, trace.ys, where="post", label=trace.label)
            else:
                (line,) = ax.plot(trace.xs, trace.ys, label=trace.label, linewidth=1.2)
            line.set_gid(trace.label)
        ax.set_ylabel(panel.ylabel)
        if panel.ticks:
            ax.set_yticks([v for v, _ in panel.ticks], [t for _, t in panel.ticks], fontsize=7)
        ax.grid(True, alpha=0.3)
        ax.legend(loc="best", fontsize=8)
    axes[-1].set_xlabel("time from trigger [s]")
    fig.suptitle(title, fontsize=10)
    return fig


# --- HTML ----------------------------------------------------------------------------

WIDTH, HEIGHT, LEFT, RIGHT, TOP, BOTTOM = 900, 220, 150, 20, 10, 30
COLOURS = ("#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b")


def nice_ticks(lo: float, hi: float, count: int = 5) -> list[float]:
    """Round tick values between lo and hi (1, 2, 5 times a power of ten apart)."""
    if not hi > lo:
        return [lo]
    raw = (hi - lo) / count
    step = 10 ** math.floor(math.log10(raw))
    for m in (1, 2, 5, 10):
        if m * step >= raw:
            step *= m
            break
    first = math.ceil(lo / step) * step
    return [round(first + k * step, 12) for k in range(int((hi - first) / step + 1e-9) + 1)]


def _points(trace: Trace) -> str:
    pts: list[tuple[float, float]] = []
    for k, (x, y) in enumerate(zip(trace.xs, trace.ys)):
        if trace.step and k:
            pts.append((x, trace.ys[k - 1]))
        pts.append((x, y))
    return " ".join(f"{x:.6g},{-y:.6g}" for x, y in pts)  # SVG's y grows downwards


def _panel_svg(panel: Panel, x0: float, x1: float) -> str:
    ys = [y for t in panel.traces for y in t.ys]
    lo, hi = (min(ys), max(ys)) if ys else (0.0, 1.0)
    if panel.ticks:
        lo, hi = min(lo, panel.ticks[0][0]), max(hi, panel.ticks[-1][0])
    if hi == lo:
        lo, hi = lo - 1, hi + 1
    pad = (hi - lo) * 0.05
    lo, hi = lo - pad, hi + pad
    pw, ph = WIDTH - LEFT - RIGHT, HEIGHT - TOP - BOTTOM
    ticks = panel.ticks or tuple((v, f"{v:g}") for v in nice_ticks(lo, hi))
    parts = [f'<svg class="panel" width="{WIDTH}" height="{HEIGHT}" data-ylabel="{html.escape(panel.ylabel)}">',
             f'<rect x="{LEFT}" y="{TOP}" width="{pw}" height="{ph}" fill="none" stroke="#888"/>']
    for v, text in ticks:
        y = TOP + ph * (hi - v) / (hi - lo)
        parts.append(f'<line x1="{LEFT - 4}" x2="{LEFT + pw}" y1="{y:.1f}" y2="{y:.1f}" stroke="#ddd"/>'
                     f'<text x="{LEFT - 6}" y="{y + 4:.1f}" text-anchor="end">{html.escape(text)}</text>')
    parts.append(f'<text x="12" y="{TOP + ph / 2:.0f}" transform="rotate(-90 12 {TOP + ph / 2:.0f})" '
                 f'text-anchor="middle">{html.escape(panel.ylabel)}</text>')
    parts.append(f'<g class="xticks" transform="translate(0 {TOP + ph})"></g>')
    parts.append(f'<svg class="plot" x="{LEFT}" y="{TOP}" width="{pw}" height="{ph}" '
                 f'viewBox="{x0:.6g} {-hi:.6g} {x1 - x0:.6g} {hi - lo:.6g}" preserveAspectRatio="none">')
    for k, trace in enumerate(panel.traces):
        colour = COLOURS[k % len(COLOURS)]
        parts.append(f'<polyline data-label="{html.escape(trace.label)}" fill="none" stroke="{colour}" '
                     f'stroke-width="1.5" vector-effect="non-scaling-stroke" points="{_points(trace)}"/>')
    parts.append("</svg>")
    for k, trace in enumerate(panel.traces):
        parts.append(f'<text x="{LEFT + 8}" y="{TOP + 16 + 14 * k}" fill="{COLOURS[k % len(COLOURS)]}">'
                     f'{html.escape(trace.label)}</text>')
    parts.append("</svg>")
    return "".join(parts)


# Drag across any axis to zoom the time axis of all; double-click to reset.
_SCRIPT = """
const L=%d,PW=%d,FULL=%s;let view=FULL.slice(),drag=null;
function ticks(lo,hi){const raw=(hi-lo)/8,p=Math.pow(10,Math.floor(Math.log10(raw)));
 let s=p;for(const m of [1,2,5,10]){if(m*p>=raw){s=m*p;break;}}const out=[];
 for(let v=Math.ceil(lo/s)*s;v<=hi+1e-12;v+=s)out.push(+v.toPrecision(12));return out;}
function show(){for(const svg of document.querySelectorAll('svg.panel')){
 const plot=svg.querySelector('svg.plot'),vb=plot.getAttribute('viewBox').split(' ');
 plot.setAttribute('viewBox',[view[0],vb[1],view[1]-view[0],vb[3]].join(' '));
 const g=svg.querySelector('g.xticks');g.innerHTML='';
 for(const v of ticks(view[0],view[1])){const x=L+PW*(v-view[0])/(view[1]-view[0]);
  g.innerHTML+=`<line x1="${x}" x2="${x}" y1="0" y2="5" stroke="#888"/>`+
  `<text x="${x}" y="18" text-anchor="middle">${v}</text>`;}}}
function at(e,svg){const r=svg.getBoundingClientRect();
 return view[0]+(view[1]-view[0])*Math.min(Math.max((e.clientX-r.left-L)/PW,0),1);}
for(const svg of document.querySelectorAll('svg.panel')){
 svg.addEventListener('mousedown',e=>{drag=at(e,svg);e.preventDefault();});
 svg.addEventListener('mouseup',e=>{if(drag===null)return;const t=at(e,svg);
  if(Math.abs(t-drag)>1e-9)view=[Math.min(t,drag),Math.max(t,drag)];drag=null;show();});
 svg.addEventListener('dblclick',()=>{view=FULL.slice();show();});}
show();
"""


def html_page(found: Sequence[Panel], title: str) -> str:
    xs = [x for p in found for t in p.traces for x in t.xs]
    x0, x1 = (min(xs), max(xs)) if xs else (0.0, 1.0)
    if x1 == x0:
        x1 = x0 + 1.0
    body = "\n".join(_panel_svg(p, x0, x1) for p in found)
    script = _SCRIPT % (LEFT, WIDTH - LEFT - RIGHT, json.dumps([x0, x1]))
    return ("<!DOCTYPE html>\n<html><head><meta charset=\"utf-8\">"
            f"<title>{html.escape(title)}</title><style>body{{font:13px sans-serif}}"
            "svg.panel{display:block;user-select:none}</style></head><body>"
            f"<h3>{html.escape(title)}</h3><p>time from trigger [s]; drag across an axis to zoom, "
            f"double-click to show all</p>\n{body}\n<script>{script}</script></body></html>\n")


__all__ = ["FORMATS", "Panel", "PlotUnavailable", "Trace", "figure", "html_page", "nice_ticks",
           "panels", "write_plot"]
