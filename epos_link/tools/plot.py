"""Plots of a recording: PNG or SVG through matplotlib, or one self-contained HTML file.

What an engineer reading a recording expects (issue 34 item 3; the habits of EPOS
Studio's Data Recorder and PlotJuggler), decided once here for both outputs
(:func:`panels`):

* **One axis per physical quantity**: the objects that share a unit share an
  axis; an object without a unit has its own; all over the same time axis.
* **The state as a thin band**: the statusword becomes its CiA 402 state
  (CiA 402-2 6.4.1.4), drawn as a strip of coloured spans named by state, a
  fraction of a quantity's height, not a panel of its own.
* **A mark at the trigger**: a dashed vertical line at time 0 labelled
  "trigger", on every axis; none when the recording was never triggered
  (interrupted while waiting: time 0 is then the last sample, not a trigger).
* **Gaps, not straight lines, where samples are missing**: with a sampling
  period, consecutive samples more than 1.5 periods apart have at least one
  missed slot between them (the sampler skips slots it cannot take, it never
  catches up: :class:`epos_link.tools.recording.Schedule`); the usual step is the
  median interval instead when the link cannot keep the period (:func:`gap_limit`).
  Without a period (as fast as the link allows), a pause of more than
  :data:`STALL_FACTOR` median intervals is a stall. A gap is a break in every
  trace (a NaN point in the middle of the gap) and a light grey span, so no line
  is drawn across time when nothing was measured; a sample alone between two
  gaps is drawn as a dot.
* **Legends off the data**: matplotlib puts them to the right of each axis,
  outside it; the HTML page under each chart.
* HTML only: **a cursor with the values at its time** (all charts follow it),
  zoom by dragging across a chart (all charts follow), double-click to show all.

Values that are not numbers (strings, bytes) are not drawn.

* PNG/SVG: matplotlib, an optional dependency (``pip install 'epos-link[plot]'``);
  without it :class:`PlotUnavailable` says so. Each line carries its object's
  name as its gid, so an SVG names its traces (``<g id="...">``).
* HTML: :mod:`epos_link.tools.plot_html`, uPlot (vendored in
  :mod:`epos_link.vendor`) and the data inlined: no script or style from the network.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional, Sequence

from ..cia402 import State, state_text
from ..errors import LocalProtocolError
from .recording import Channel, Value, median_interval, state_of

FORMATS = (".png", ".svg", ".html", ".htm")
STATE_AXIS = "CiA 402 state"
NO_STATE = -1  # a statusword that codes no state
SLOT_FACTOR = 1.5  # a step of more than 1.5 periods skipped at least one slot
STALL_FACTOR = 3.0  # without a period: a pause of 3 median intervals is a gap
GAP = math.nan

# One colour per CiA 402 state (fault red, operation enabled green, the rest muted).
STATE_COLOURS = {
    NO_STATE: "#bbbbbb", int(State.NOT_READY_TO_SWITCH_ON): "#d9d9d9",
    int(State.SWITCH_ON_DISABLED): "#c6dbef", int(State.READY_TO_SWITCH_ON): "#9ecae1",
    int(State.SWITCHED_ON): "#6baed6", int(State.OPERATION_ENABLED): "#74c476",
    int(State.QUICK_STOP_ACTIVE): "#fdae6b", int(State.FAULT_REACTION_ACTIVE): "#fb6a4a",
    int(State.FAULT): "#cb181d",
}


class PlotUnavailable(LocalProtocolError):
    """matplotlib is not installed, or the file name asks for a format we do not draw."""


@dataclass(frozen=True)
class Trace:
    label: str
    xs: tuple[float, ...]
    ys: tuple[float, ...]  # NaN: no value (a gap, see the module docstring)
    step: bool = False


@dataclass(frozen=True)
class Panel:
    ylabel: str
    traces: tuple[Trace, ...]
    ticks: Optional[tuple[tuple[float, str], ...]] = None  # state codes and their names
    band: bool = False  # the CiA 402 state strip

    @property
    def unit(self) -> str:
        return self.ylabel.rsplit("[", 1)[1].rstrip("]") if self.ylabel.endswith("]") else ""


@dataclass(frozen=True)
class Span:
    """A stretch of one state in the band: [start, end) and its state code."""

    start: float
    end: float
    state: int


def _number(value: Value) -> Optional[float]:
    if isinstance(value, bool):
        return float(value)
    if isinstance(value, (int, float)) and math.isfinite(value):
        return float(value)
    return None


def gap_limit(times: Sequence[float], period: float = 0.0) -> Optional[float]:
    """The longest step between two samples that is not a gap (None: no gaps).

    With a period: 1.5 times the usual step, which is the period, or the median
    interval when the link cannot keep the period (a link that takes every second
    slot samples every 2 periods; only what it skipped beyond that is a gap, or a
    recording at a steady 2 periods would be nothing but gaps)."""
    typical = median_interval(times)
    if period > 0:
        return SLOT_FACTOR * max(period, typical or 0.0)
    return STALL_FACTOR * typical if typical else None


def gaps(times: Sequence[float], period: float = 0.0) -> list[tuple[float, float]]:
    """(last sample before, first sample after) of each gap."""
    limit = gap_limit(times, period)
    if limit is None:
        return []
    return [(a, b) for a, b in zip(times, times[1:]) if b - a > limit]


def panels(channels: Sequence[Channel], rows: Sequence[tuple[float, Sequence[Value]]], *,
           period: float = 0.0) -> list[Panel]:
    """The axes of a plot, in the order their objects were named; the state band last."""
    times = [t for t, _ in rows]
    holes = {a for a, _ in gaps(times, period)}
    # Each gap gets one point in its middle with no value: a break in every trace.
    xs: list[float] = []
    for k, t in enumerate(times):
        xs.append(t)
        if t in holes and k + 1 < len(times):
            xs.append((t + times[k + 1]) / 2)

    def spread(values: Sequence[float]) -> tuple[float, ...]:
        out: list[float] = []
        for k, (t, v) in enumerate(zip(times, values)):
            out.append(v)
            if t in holes and k + 1 < len(times):
                out.append(GAP)
        return tuple(out)

    order: list[str] = []
    groups: dict[str, list[Trace]] = {}
    state_trace: Optional[Trace] = None
    seen_states: set[int] = set()
    for i, ch in enumerate(channels):
        if ch.is_statusword:
            states = [state_of(v[i]) for _, v in rows]
            codes = [float(NO_STATE if s is None else int(s)) for s in states]
            seen_states.update(int(c) for c in codes)
            state_trace = Trace(f"{ch.name} state", tuple(xs), spread(codes), step=True)
            continue
        numbers = [_number(v[i]) for _, v in rows]
        if not rows or any(n is None for n in numbers):
            continue
        key = f"[{ch.unit}]" if ch.unit else ch.name  # an axis per unit, else per object
        if key not in groups:
            groups[key] = []
            order.append(key)
        groups[key].append(Trace(ch.name, tuple(xs), spread([n for n in numbers if n is not None])))
    out = []
    for key in order:
        traces = tuple(groups[key])
        one = len(traces) == 1 and key.startswith("[")  # "position actual value [inc]"
        out.append(Panel(f"{traces[0].label} {key}" if one else key, traces))
    if state_trace is not None:
        ticks = tuple((float(s), state_text(None if s == NO_STATE else State(s)))
                      for s in sorted(seen_states))
        out.append(Panel(STATE_AXIS, (state_trace,), ticks, band=True))
    return out


def isolated(trace: Trace) -> list[int]:
    """Indices of the samples with no neighbour to draw a line to (NaN or none)."""
    ys, last = trace.ys, len(trace.ys) - 1
    return [k for k, y in enumerate(ys) if not math.isnan(y)
            and (k == 0 or math.isnan(ys[k - 1])) and (k == last or math.isnan(ys[k + 1]))
            and last > 0]


def spans(trace: Trace) -> list[Span]:
    """The band's stretches of one state: each sample's state lasts until the next
    sample (a step, as the statusword was read); a gap ends a stretch at the sample
    before it."""
    out: list[Span] = []
    for k in range(len(trace.xs) - 1):
        y = trace.ys[k]
        if math.isnan(y):
            continue
        start, code = trace.xs[k], int(y)
        # Before a gap nothing is known after the sample itself: lines stop there too.
        end = start if math.isnan(trace.ys[k + 1]) else trace.xs[k + 1]
        if out and out[-1].state == code and out[-1].end == start:
            out[-1] = Span(out[-1].start, end, code)
        else:
            out.append(Span(start, end, code))
    return out


def gap_spans(found: Sequence[Panel]) -> list[tuple[float, float]]:
    """The (start, end) of each gap, from the traces (NaN points and their neighbours)."""
    for panel in found:
        for trace in panel.traces:
            return [(trace.xs[k - 1], trace.xs[k + 1]) for k in range(1, len(trace.ys) - 1)
                    if math.isnan(trace.ys[k])]
    return []


def write_plot(path: str, found: Sequence[Panel], title: str, *,
               trigger: Optional[float] = 0.0) -> None:
    """``trigger``: where the trigger mark goes (None: the recording was not triggered)."""
    suffix = Path(path).suffix.lower()
    if suffix in (".html", ".htm"):
        from .plot_html import html_page

        Path(path).write_text(html_page(found, title, trigger=trigger), encoding="utf-8")
    elif suffix in (".png", ".svg"):
        figure(found, title, trigger=trigger).savefig(path, dpi=80)
    else:
        raise PlotUnavailable(f"{path}: a plot is .png, .svg or .html")


# --- matplotlib ------------------------------------------------------------------------


def figure(found: Sequence[Panel], title: str, *, trigger: Optional[float] = 0.0) -> Any:
    """A matplotlib Figure (no pyplot, so no global state and no display needed)."""
    try:
        from matplotlib.figure import Figure
        from matplotlib.patches import Patch
    except ImportError:
        raise PlotUnavailable("PNG and SVG plots need matplotlib: pip install 'epos-link[plot]' "
                              "(or pip install matplotlib); an .html plot needs nothing") from None
    shown = list(found) or [Panel("", ())]
    ratios = [0.35 if p.band else 1.0 for p in shown]
    fig = Figure(figsize=(10.0, 0.8 + sum(2.2 * r for r in ratios)), layout="constrained")
    axes = fig.subplots(len(shown), 1, sharex=True, squeeze=False,
                        gridspec_kw={"height_ratios": ratios})[:, 0]
    holes = gap_spans(shown)
    for ax, panel in zip(axes, shown):
        if panel.band:
            _band(ax, panel, Patch)
        else:
            for trace in panel.traces:
                (line,) = ax.plot(trace.xs, trace.ys, label=trace.label, linewidth=1.2)
                line.set_gid(trace.label)
                alone = isolated(trace)
                if alone:  # no line reaches a sample alone between two gaps: a dot
                    ax.plot([trace.xs[k] for k in alone], [trace.ys[k] for k in alone],
                            linestyle="", marker="o", markersize=2.5, color=line.get_color(),
                            gid=f"{trace.label} (alone)")
            ax.set_ylabel(panel.ylabel, fontsize=9)
            ax.grid(True, alpha=0.3)
            # Off the data: to the right, outside the axes.
            ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0,
                      fontsize=8, frameon=False)
        for k, (a, b) in enumerate(holes):
            ax.axvspan(a, b, color="#999999", alpha=0.15, linewidth=0,
                       gid="gap" if k == 0 else None)
        if trigger is not None:
            ax.axvline(trigger, color="#333333", linestyle="--", linewidth=0.9, gid="trigger")
    if trigger is not None:
        axes[0].annotate("trigger", xy=(trigger, 1.0), xycoords=("data", "axes fraction"),
                         xytext=(3, -10), textcoords="offset points", fontsize=8, color="#333333")
    axes[-1].set_xlabel("time from trigger [s]" if trigger is not None else
                        "time [s] (not triggered: 0 is the last sample)")
    missed = f"; {len(holes)} gap{'s' if len(holes) != 1 else ''} (missed samples, grey)" \
        if holes else ""
    fig.suptitle(title + missed, fontsize=10)
    return fig


def _band(ax: Any, panel: Panel, patch: Any) -> None:
    trace = panel.traces[0]
    names = dict(panel.ticks or ())
    found = spans(trace)
    lo, hi = (trace.xs[0], trace.xs[-1]) if trace.xs else (0.0, 1.0)
    width = (hi - lo) or 1.0
    for span in found:
        ax.broken_barh([(span.start, span.end - span.start)], (0, 1),
                       facecolors=STATE_COLOURS.get(span.state, "#bbbbbb"), gid=trace.label)
        if (span.end - span.start) / width > 0.12:  # a name only where it fits
            ax.text((span.start + span.end) / 2, 0.5, names.get(float(span.state), ""),
                    ha="center", va="center", fontsize=7, clip_on=True)
    ax.set_ylim(0, 1)
    ax.set_yticks([])
    ax.set_ylabel("state", fontsize=9, rotation=0, ha="right", va="center")
    used = sorted({s.state for s in found})
    ax.legend(handles=[patch(color=STATE_COLOURS.get(s, "#bbbbbb"), label=names.get(float(s), ""))
                       for s in used],
              loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0, fontsize=7,
              frameon=False)


__all__ = ["FORMATS", "GAP", "Panel", "PlotUnavailable", "STATE_AXIS", "STATE_COLOURS", "Span",
           "Trace", "figure", "gap_limit", "gap_spans", "gaps", "isolated", "panels", "spans", "write_plot"]
