"""The plots of ``epos-link record`` (epos_link/tools/plot.py), checked from the figure, the
SVG and the HTML, not by eye: one axis per physical quantity, the expected traces, the
statusword as a step trace of its CiA 402 state."""
from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from html.parser import HTMLParser
from pathlib import Path

import pytest

from epos_link.tools.plot import STATE_AXIS, html_page, nice_ticks, panels, write_plot
from epos_link.tools.recording import Channel

CHANNELS = [Channel(0x6064, 0, "position actual value", "inc"),
            Channel(0x6062, 0, "position demand value", "inc"),
            Channel(0x606C, 0, "velocity actual value", "rpm"),
            Channel(0x6041, 0, "statusword"),
            Channel(0x2000, 0, "0x2000/0x00")]
ROWS = [(-0.01, (0, 0, 0, 0x0040, 1)), (0.0, (0, 5, 10, 0x0037, 2)),
        (0.01, (7, 12, 20, 0x1037, 3)), (0.02, (20, 20, 0, 0x0437, 4))]


def test_one_axis_per_quantity_and_the_state_axis() -> None:
    found = panels(CHANNELS, ROWS)
    assert [p.ylabel for p in found] == ["[inc]", "velocity actual value [rpm]", STATE_AXIS, "0x2000/0x00"]
    assert [t.label for t in found[0].traces] == ["position actual value", "position demand value"]
    state = found[2].traces[0]
    assert state.step and state.ys == (1.0, 4.0, 4.0, 4.0)  # switch on disabled, then operation enabled
    assert found[2].ticks is not None and (4.0, "operation enabled") in found[2].ticks


def test_png_and_svg_from_matplotlib(tmp_path: Path) -> None:
    pytest.importorskip("matplotlib", reason="needs matplotlib: pip install 'epos-link[plot]'")
    from epos_link.tools.plot import figure

    fig = figure(panels(CHANNELS, ROWS), "node 2")
    axes = fig.get_axes()
    assert [ax.get_ylabel() for ax in axes] == ["[inc]", "velocity actual value [rpm]", STATE_AXIS, "0x2000/0x00"]
    assert [ln.get_gid() for ln in axes[0].get_lines()] == ["position actual value", "position demand value"]
    assert list(axes[0].get_lines()[0].get_ydata()) == [0, 0, 7, 20]
    assert axes[2].get_lines()[0].get_drawstyle() == "steps-post"
    assert "operation enabled" in [t.get_text() for t in axes[2].get_yticklabels()]
    png, svg = tmp_path / "r.png", tmp_path / "r.svg"
    write_plot(str(png), panels(CHANNELS, ROWS), "node 2")
    write_plot(str(svg), panels(CHANNELS, ROWS), "node 2")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    root = ET.parse(svg).getroot()  # well-formed XML
    ids = {el.get("id") for el in root.iter()}
    assert {"position actual value", "velocity actual value", "statusword state"} <= ids


class _Panels(HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.panels: list[str] = []
        self.lines: list[tuple[str, str]] = []
        self.external: list[str] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        a = dict(attrs)
        if tag == "svg" and a.get("class") == "panel":
            self.panels.append(a["data-ylabel"] or "")
        if tag == "polyline":
            self.lines.append((self.panels[-1], a["data-label"] or ""))
        if tag in ("script", "link", "img") and (a.get("src") or a.get("href")):
            self.external.append(tag)


def test_html_is_self_contained_with_the_axes_and_traces() -> None:
    page = html_page(panels(CHANNELS, ROWS), "node 2")
    parsed = _Panels()
    parsed.feed(page)
    assert parsed.panels == ["[inc]", "velocity actual value [rpm]", STATE_AXIS, "0x2000/0x00"]
    assert parsed.lines == [("[inc]", "position actual value"), ("[inc]", "position demand value"),
                            ("velocity actual value [rpm]", "velocity actual value"),
                            (STATE_AXIS, "statusword state"), ("0x2000/0x00", "0x2000/0x00")]
    assert parsed.external == [] and "http" not in page
    # the state trace is drawn as steps: each change is a vertical segment at its time
    state = re.search(r'data-label="statusword state"[^>]*points="([^"]*)"', page)
    assert state is not None and state.group(1).split() == ["-0.01,-1", "0,-1", "0,-4", "0.01,-4",
                                                            "0.01,-4", "0.02,-4", "0.02,-4"]


def test_nice_ticks() -> None:
    assert nice_ticks(0, 1) == [0, 0.2, 0.4, 0.6, 0.8, 1.0]
    assert nice_ticks(-3, 17) == [0, 5, 10, 15]


def test_an_unknown_plot_format_is_refused(tmp_path: Path) -> None:
    from epos_link.tools.plot import PlotUnavailable

    with pytest.raises(PlotUnavailable):
        write_plot(str(tmp_path / "r.jpg"), panels(CHANNELS, ROWS), "x")
