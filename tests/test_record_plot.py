"""The plots of ``epos-link record`` (epos_link/tools/plot.py, plot_html.py), checked from the
figure, the SVG and the HTML, not by eye: one axis per physical quantity, the statusword
as a thin band of CiA 402 states, a mark at the trigger, gaps where samples are missing,
legends off the data. tests/test_record_plot_browser.py checks the HTML in chromium."""
from __future__ import annotations

import argparse
import json
import math
import re
import xml.etree.ElementTree as ET
from html.parser import HTMLParser
from pathlib import Path
from typing import Any, Dict

import pytest

from epos_link.tools.plot import (STATE_AXIS, Span, gap_spans, gaps, panels, spans,
                                  write_plot)
from epos_link.tools.plot_html import html_page
from epos_link.tools.record_output import write_outputs
from epos_link.tools.recording import Channel

CHANNELS = [Channel(0x6064, 0, "position actual value", "inc"),
            Channel(0x6062, 0, "position demand value", "inc"),
            Channel(0x606C, 0, "velocity actual value", "rpm"),
            Channel(0x6041, 0, "statusword"),
            Channel(0x2000, 0, "0x2000/0x00")]
ROWS = [(-0.01, (0, 0, 0, 0x0040, 1)), (0.0, (0, 5, 10, 0x0037, 2)),
        (0.01, (7, 12, 20, 0x1037, 3)), (0.02, (20, 20, 0, 0x0437, 4))]
# Sampled every 10 ms; the slots at 0.03 and 0.04 were missed.
GAPPY = ROWS + [(0.05, (30, 30, 0, 0x0437, 5)), (0.06, (31, 31, 0, 0x0437, 6))]


def plot_panels(page: str) -> list:
    """The panels of an HTML plot, from its inlined data (for other tests too)."""
    parsed = _Page()
    parsed.feed(page)
    return list(parsed.data["panels"])


def test_one_axis_per_quantity_and_the_state_band_last() -> None:
    found = panels(CHANNELS, ROWS)
    assert [p.ylabel for p in found] == ["[inc]", "velocity actual value [rpm]", "0x2000/0x00",
                                         STATE_AXIS]
    assert [t.label for t in found[0].traces] == ["position actual value", "position demand value"]
    band = found[3]
    assert band.band and not any(p.band for p in found[:3])
    assert band.traces[0].ys == (1.0, 4.0, 4.0, 4.0)  # switch on disabled, then operation enabled
    assert band.ticks == ((1.0, "switch on disabled"), (4.0, "operation enabled"))
    assert spans(band.traces[0]) == [Span(-0.01, 0.0, 1), Span(0.0, 0.02, 4)]


@pytest.mark.parametrize("period, times, expected", [
    (0.01, [0, 0.01, 0.02, 0.05, 0.06], [(0.02, 0.05)]),  # two slots missed
    (0.01, [0, 0.01, 0.02, 0.03], []),
    (0.01, [0, 0.014, 0.028], []),  # late, but no slot skipped
    (0.0, [0, 0.002, 0.004, 0.006, 0.02, 0.022], [(0.006, 0.02)]),  # a stall of 7 intervals
    (0.0, [0, 0.002, 0.005, 0.007, 0.010], []),  # jitter is no stall
    (0.0, [0.0], []),
])
def test_gaps_are_missed_slots_or_stalls(period: float, times: list, expected: list) -> None:
    assert gaps(times, period) == expected


def test_a_gap_breaks_every_trace_and_the_band() -> None:
    found = panels(CHANNELS, GAPPY, period=0.01)
    for panel in found:
        for trace in panel.traces:
            assert trace.xs[4] == pytest.approx(0.035) and math.isnan(trace.ys[4])
            assert sum(math.isnan(y) for y in trace.ys) == 1
    assert gap_spans(found) == [(0.02, 0.05)]
    # The state stops at the last sample before the gap and starts again after it.
    assert spans(found[3].traces[0]) == [Span(-0.01, 0.0, 1), Span(0.0, 0.02, 4),
                                         Span(0.05, 0.06, 4)]


def test_png_and_svg_from_matplotlib(tmp_path: Path) -> None:
    pytest.importorskip("matplotlib", reason="needs matplotlib: pip install 'epos-link[plot]'")
    from epos_link.tools.plot import figure

    fig = figure(panels(CHANNELS, GAPPY, period=0.01), "node 2")
    axes = fig.get_axes()
    assert [ax.get_ylabel() for ax in axes] == ["[inc]", "velocity actual value [rpm]",
                                                "0x2000/0x00", "state"]
    lines = [ln for ln in axes[0].get_lines() if ln.get_gid() not in ("trigger",)]
    assert [ln.get_gid() for ln in lines] == ["position actual value", "position demand value"]
    ys = list(lines[0].get_ydata())
    assert ys[:4] == [0, 0, 7, 20] and math.isnan(ys[4]) and ys[5:] == [30, 31]
    # The trigger mark: a vertical line at 0 on every axis, named once.
    for ax in axes:
        assert [list(ln.get_xdata()) for ln in ax.get_lines() if ln.get_gid() == "trigger"] \
            == [[0, 0]]
    assert "trigger" in [t.get_text() for t in axes[0].texts]
    # The band is a fraction of a quantity's height; its spans are coloured by state.
    heights = [ax.get_position().height for ax in axes]
    assert heights[3] < 0.5 * heights[0]
    assert [t.get_text() for t in axes[3].get_legend().get_texts()] == ["switch on disabled",
                                                                         "operation enabled"]
    # Legends off the data: each begins right of its axes.
    fig.canvas.draw()
    for ax in axes:
        legend = ax.get_legend().get_window_extent()
        assert legend.x0 >= ax.get_window_extent().x1
    png, svg = tmp_path / "r.png", tmp_path / "r.svg"
    write_plot(str(png), panels(CHANNELS, ROWS), "node 2")
    write_plot(str(svg), panels(CHANNELS, ROWS), "node 2", trigger=None)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    root = ET.parse(svg).getroot()  # well-formed XML
    ids = {el.get("id") for el in root.iter()}
    assert {"position actual value", "velocity actual value", "statusword state"} <= ids
    assert "trigger" not in ids  # not triggered: no mark


class _Page(HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.external: list[str] = []
        self.data: Dict[str, Any] = {}
        self._in_data = False

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        a = dict(attrs)
        if a.get("src") or a.get("href"):
            self.external.append(tag)
        self._in_data = tag == "script" and a.get("id") == "plot-data"

    def handle_data(self, data: str) -> None:
        if self._in_data:
            self.data = json.loads(data)
            self._in_data = False


def test_html_is_self_contained_with_the_charts_data() -> None:
    page = html_page(panels(CHANNELS, GAPPY, period=0.01), "node 2 </script><b>")
    parsed = _Page()
    parsed.feed(page)
    assert parsed.external == []  # uPlot and its CSS are inlined: no CDN, no file beside it
    assert "uPlot" in page and "MIT" in page and "epos_link/vendor/uplot/LICENSE" in page
    assert page.count("</script>") == 3  # the title cannot close a script early
    data = parsed.data
    assert data["title"] == "node 2 </script><b>" and data["trigger"] == 0.0
    assert [p["ylabel"] for p in data["panels"]] == ["[inc]", "velocity actual value [rpm]",
                                                     "0x2000/0x00", STATE_AXIS]
    assert [s["label"] for s in data["panels"][0]["series"]] == ["position actual value",
                                                                 "position demand value"]
    assert data["panels"][0]["series"][0]["ys"] == [0, 0, 7, 20, None, 30, 31]
    assert data["panels"][3]["band"] and data["panels"][3]["states"] == {
        "1": "switch on disabled", "4": "operation enabled"}
    assert data["gaps"] == [[0.02, 0.05]]
    assert re.search(r"1 gap where samples are missing", page)


def test_record_outputs_mark_the_trigger_only_when_there_was_one(tmp_path: Path) -> None:
    args = argparse.Namespace(csv=None, plot=[str(tmp_path / "r.html")], period=0.01)
    write_outputs(args, CHANNELS, GAPPY, "x", triggered=False)
    parsed = _Page()
    parsed.feed((tmp_path / "r.html").read_text())
    assert parsed.data["trigger"] is None and parsed.data["gaps"] == [[0.02, 0.05]]
    assert "not triggered" in (tmp_path / "r.html").read_text()


def test_an_unknown_plot_format_is_refused(tmp_path: Path) -> None:
    from epos_link.tools.plot import PlotUnavailable

    with pytest.raises(PlotUnavailable):
        write_plot(str(tmp_path / "r.jpg"), panels(CHANNELS, ROWS), "x")


def test_a_link_that_keeps_every_second_slot_is_no_gap_and_a_lone_sample_is_a_dot() -> None:
    from epos_link.tools.plot import Trace, isolated

    steady = [k * 0.01 for k in range(10)]  # --period 0.005, every second slot taken
    assert gaps(steady, 0.005) == []
    assert gaps(steady[:5] + [0.08, 0.09], 0.005) == [(0.04, 0.08)]
    nan = math.nan
    assert isolated(Trace("x", (0, 1, 2, 3, 4), (1.0, nan, 2.0, nan, 3.0))) == [0, 2, 4]
    assert isolated(Trace("x", (0, 1, 2), (1.0, 2.0, nan))) == []
