"""The HTML plot of a recording in a real browser (issue 34, Must show 3): headless
chromium over DevTools (tests/cdp.py) opens the file ``epos-link record --plot r.html``
writes, moves the mouse over it as a person would, and reads what the page shows:

* the cursor's readout: the legends under the charts give the time and each trace's
  value of the sample under the mouse;
* the trigger mark at time 0 (``div.trigger``, labelled "trigger");
* a gap where sampling slots were missed: no trace pixel is drawn in its middle
  (it would be, were the two samples around it joined by a straight line), while
  the same trace is drawn beside it.

Skipped, with the reason, where no chromium is installed (Debian: ``apt install chromium``).
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any, Iterator, List, Tuple

import pytest

from epos_link.tools.record_output import write_outputs
from epos_link.tools.recording import Channel
from tests.cdp import Chromium, find_chromium

CHROMIUM = find_chromium()
pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="no chromium binary on PATH "
                                "(Debian: apt install chromium); the plot's browser test "
                                "cannot run")

PERIOD = 0.01
MISSED = range(40, 46)  # slots 40..45 were missed: nothing between t=0.39 and t=0.46
CHANNELS = [Channel(0x6064, 0, "position actual value", "inc"),
            Channel(0x606C, 0, "velocity actual value", "rpm"),
            Channel(0x6041, 0, "statusword")]


def recording() -> List[Tuple[float, Tuple[int, int, int]]]:
    """A move starting at the trigger (t = 0), sampled every 10 ms, six slots missed."""
    rows = []
    for k in range(-20, 100):
        if k in MISSED:
            continue
        t = round(k * PERIOD, 9)
        pos = 0 if t < 0 else int(5000 * min(t, 0.6) ** 2)
        vel = 0 if t < 0 else int(1000 * min(t, 0.6))
        rows.append((t, (pos, vel, 0x0040 if k < -10 else 0x0437 if k >= 70 else 0x1037)))
    return rows


def wait_for(what: Any, timeout: float, why: str) -> Any:
    deadline = time.monotonic() + timeout
    while True:
        value = what()
        if value:
            return value
        assert time.monotonic() < deadline, f"{why} (within {timeout} s)"
        time.sleep(0.1)


@pytest.fixture
def page(tmp_path: Path) -> Iterator[Chromium]:
    """The plot as ``record`` writes it (write_outputs, with its --period), in chromium."""
    args = argparse.Namespace(csv=None, plot=[str(tmp_path / "r.html")], period=PERIOD)
    written = write_outputs(args, CHANNELS, recording(), "node 2: a move", triggered=True)
    assert written.paths == [str(tmp_path / "r.html")] and not written.failed
    assert CHROMIUM is not None
    browser = Chromium(CHROMIUM, tmp_path / "profile", size="1200,900")
    try:
        browser.call("Page.navigate", url=(tmp_path / "r.html").as_uri())
        wait_for(lambda: browser.evaluate("(window.plotCharts || []).length") == 3, 60,
                 "the plot's three charts were not drawn")
        yield browser
    finally:
        browser.close()


def x_on_screen(browser: Chromium, chart: int, t: float) -> Tuple[float, float]:
    """Page coordinates of time ``t`` in the middle of ``chart``'s plotting area."""
    return browser.evaluate(
        f"(() => {{const u = plotCharts[{chart}], r = u.over.getBoundingClientRect();"
        f" return [r.left + u.valToPos({t}, 'x'), r.top + r.height / 2];}})()")


def legend(browser: Chromium, chart: int) -> List[str]:
    return browser.evaluate(
        f"Array.from(plotCharts[{chart}].root.querySelectorAll('.u-legend .u-value'))"
        ".map(e => e.textContent)")


def test_the_cursor_reads_out_the_values_at_its_time_on_every_chart(page: Chromium,
                                                                    tmp_path: Path) -> None:
    x, y = x_on_screen(page, 0, 0.25)
    page.call("Input.dispatchMouseEvent", type="mouseMoved", x=x, y=y)
    # Sample at 0.25 s: position 5000 * 0.25^2 = 312, velocity 250 rpm, operation enabled.
    wait_for(lambda: legend(page, 0) == ["0.25", "312"], 30,
             f"the position chart's readout is {legend(page, 0)}")
    assert legend(page, 1) == ["0.25", "250"]  # the cursor is synchronised across charts
    assert legend(page, 2) == ["0.25", "operation enabled"]  # the band names the state
    labels = page.evaluate("Array.from(plotCharts[0].root.querySelectorAll('.u-legend "
                           ".u-label')).map(e => e.textContent)")
    assert labels == ["time [s]", "position actual value [inc]"]
    page.screenshot(tmp_path / "cursor.png")
    assert page.console_errors() == []


def test_the_trigger_is_marked_at_time_zero_on_every_chart(page: Chromium) -> None:
    marks = page.evaluate(
        "plotCharts.map(u => { const m = u.over.querySelector('div.trigger');"
        " return m && [parseFloat(m.style.left), u.valToPos(0, 'x'), m.textContent]; })")
    assert len(marks) == 3 and all(m is not None for m in marks), marks
    for left, expected, _ in marks:
        assert abs(left - expected) < 1
    assert [m[2] for m in marks] == ["trigger", "", ""]


def trace_pixels(page: Chromium, chart: int, t: float, colour: Tuple[int, int, int]) -> int:
    """Pixels of ``colour`` (within a small tolerance) in the column of time ``t``."""
    return page.evaluate(
        f"(() => {{const u = plotCharts[{chart}], x = Math.round(u.valToPos({t}, 'x', true));"
        " const d = u.ctx.getImageData(x - 1, u.bbox.top, 3, u.bbox.height).data; let n = 0;"
        " for (let i = 0; i < d.length; i += 4)"
        f"  if (Math.abs(d[i] - {colour[0]}) + Math.abs(d[i + 1] - {colour[1]})"
        f"      + Math.abs(d[i + 2] - {colour[2]}) < 60) n++;"
        " return n; })()")


def test_missed_slots_are_a_gap_not_a_straight_line(page: Chromium) -> None:
    gaps = page.evaluate("Array.from(plotCharts[0].over.querySelectorAll('div.gap'))"
                         ".map(g => [+g.dataset.start, +g.dataset.end])")
    assert gaps == [[0.39, 0.46]]
    blue = (0x1F, 0x77, 0xB4)  # the first trace's colour
    assert trace_pixels(page, 0, 0.3, blue) > 0  # the trace is there beside the gap ...
    assert trace_pixels(page, 0, 0.425, blue) == 0  # ... and not across it
    assert trace_pixels(page, 1, 0.425, blue) == 0
    # The band is blank in the gap too: no state is known there.
    assert page.evaluate("(() => { const u = plotCharts[2], x = Math.round(u.valToPos(0.425, "
                         "'x', true)); const d = u.ctx.getImageData(x, u.bbox.top + "
                         "u.bbox.height / 2, 1, 1).data; return d[1] > 200 && d[0] > 200 "
                         "&& d[2] > 200 || d[3] < 50; })()")
    # The page says so in its notes.
    assert "1 gap where samples are missing" in page.evaluate("document.body.textContent")
