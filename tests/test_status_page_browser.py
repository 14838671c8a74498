"""The status page says why, in a real browser (issue 34 item 4, Must show 3).

``tcp-bridge serve --config FILE --http 127.0.0.1:0`` (the command a user types) with two
buses: the simulator (axes 1 and 2) and a CAN bus on which node 5 (axis 3) does not
answer. Headless chromium (tests/cdp.py) opens the page in a 1280 px wide window, in a
12-hour locale (en-US), as the user who met the old page had it; the test reads:

* axis 3's state cell says "silent", is coloured, and its reason is visible: the
  element at the reason's place in the 1280 px viewport is the reason itself (not
  clipped, not off-screen), and the screenshot is kept under the test's tmp_path;
* the reason is said once (not ``bus can2: bus can2: ...``);
* columns have human names with their units (no bare ``R86``); the disabled axis
  1 does not say "target reached: no"; times are 24-hour;
* the position chart has time ticks and a cursor whose readout is under the chart.

``STATUS_PAGE_SCREENSHOT=docs/status-page.png`` copies the screenshot there (how that
picture is made). Skipped, with the reason, where no chromium is installed.
"""
from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Iterator, Tuple

import pytest

from tcp_bridge.cli import send
from tcp_bridge.tables.axes import simulated_increments_per_revolution
from tcp_bridge.wire import Status
from tests.cdp import Chromium, find_chromium

CHROMIUM = find_chromium()
pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="no chromium binary on PATH "
                                "(Debian: apt install chromium); the status page's browser "
                                "test cannot run")

TABLE = """
[bridge]
state_file = "{state}"

[bus.can1]
backend = "sim"

[bus.can2]              # a CAN bus on which nobody answers: node 5 is silent
backend = "canopen"
interface = "virtual"
channel = "status-page-test-{pid}"
sdo_timeout = 0.2

[[axis]]
addr = 1
device = "maxon_epos4"
node_id = 1
position_factor = 1000
increments_per_revolution = {ipr}

[[axis]]
addr = 2
device = "maxon_epos4"
node_id = 2
position_factor = 1000
increments_per_revolution = {ipr}

[[axis]]
addr = 3
device = "maxon_epos4"
bus_offset = 100000
node_id = 5
position_factor = 1000
increments_per_revolution = {ipr}
"""


def wait_for(what: Any, timeout: float, why: str) -> Any:
    deadline = time.monotonic() + timeout
    while True:
        value = what()
        if value:
            return value
        assert time.monotonic() < deadline, f"{why} (within {timeout} s)"
        time.sleep(0.1)


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Tuple[str, str]]:
    where = tmp_path_factory.mktemp("status-page")
    table = where / "axes.toml"
    table.write_text(TABLE.format(state=where / "state.json", pid=os.getpid(),
                                  ipr=simulated_increments_per_revolution()))
    proc = subprocess.Popen([sys.executable, "-m", "tcp_bridge.cli", "serve", "--config",
                             str(table), "--port", "0", "--maintenance-port", "-1",
                             "--http", "127.0.0.1:0"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        psi = url = None
        assert proc.stdout is not None
        for line in proc.stdout:
            m = re.search(r"listening on (\S+) \(NICOS", line)
            psi = m.group(1) if m else psi
            m = re.search(r"status page at (\S+)", line)
            url = m.group(1) if m else url
            if psi and url:
                break
        assert psi and url, "serve did not say where it listens"
        yield psi, url
    finally:
        proc.terminate()
        proc.wait(60)


def test_a_silent_axis_says_so_with_its_reason_visible_at_1280_px(
        served: Tuple[str, str], tmp_path: Path) -> None:
    psi, url = served
    assert CHROMIUM is not None
    browser = Chromium(CHROMIUM, tmp_path / "profile", size="1280,800")
    try:
        browser.call("Emulation.setLocaleOverride", locale="en-US")  # a 12-hour locale
        browser.call("Emulation.setDeviceMetricsOverride", width=1280, height=800,
                     deviceScaleFactor=1, mobile=False)
        browser.call("Page.navigate", url=url)
        for reply in send(psi, ["2S04=1", "2S05=5", "2S06=100", "2S02=300", "2S00=1"],
                          timeout=30):
            assert reply.status is Status.ACK, reply
        try:
            kind = "document.getElementById('state-3')?.dataset.kind"
            wait_for(lambda: browser.evaluate(kind) == "silent", 60,
                     "axis 3's state cell never said silent")
            wait_for(lambda: browser.evaluate(
                "document.getElementById('state-2')?.textContent") == "operation enabled", 60,
                "axis 2 is not shown enabled")
            time.sleep(3 if not os.environ.get("STATUS_PAGE_SCREENSHOT") else 10)
            state = browser.evaluate("document.getElementById('state-3').firstChild.textContent")
            why = browser.evaluate("document.querySelector('#state-3 .why').textContent")
            assert state == "silent"
            assert why == "node 5 on bus can2 does not answer (No SDO response received)"
            # Visible: at the middle of the reason, the browser finds the reason itself.
            box = browser.evaluate(
                "(() => { const r = document.querySelector('#state-3 .why')"
                ".getBoundingClientRect(); return [r.left, r.top, r.right, r.bottom]; })()")
            left, top, right, bottom = box
            assert 0 <= left < right <= 1280 and 0 <= top < bottom <= 800, box
            hit = browser.evaluate(
                f"document.elementFromPoint({(left + right) / 2}, {(top + bottom) / 2})"
                ".className")
            assert hit == "why"
            colour = browser.evaluate(
                "getComputedStyle(document.getElementById('state-3')).backgroundColor")
            assert colour not in ("rgba(0, 0, 0, 0)", "rgb(255, 255, 255)"), colour
            shot = browser.screenshot(tmp_path / "silent-axis-1280.png")
            assert shot.stat().st_size > 1000
            body = browser.evaluate("document.body.innerText")
            assert "bus can2: bus can2" not in body and body.count("No SDO response") == 1

            headers = browser.evaluate(
                "Array.from(document.querySelectorAll('th')).map(th => th.textContent)")
            assert "R86" not in headers and "move started (R86)" in headers
            assert "position [user units]" in headers and "velocity [user units/s]" in headers
            assert browser.evaluate("document.getElementById('state-1').textContent") \
                == "switch on disabled"
            assert browser.evaluate("document.getElementById('reached-1').textContent") == ""
            meta = browser.evaluate("document.getElementById('meta').textContent")
            assert re.search(r" at \d\d:\d\d:\d\d, every", meta) and not re.search(
                r"AM|PM", meta), meta

            # The position chart: time ticks in 24-hour form; a cursor readout under it.
            # uPlot draws tick labels on its canvas; the texts it drew are its axis's
            # _values (uPlot 1.6 keeps them there between redraws).
            ticks = browser.evaluate("statusCharts()[0].axes[0]._values")
            assert ticks and all(re.fullmatch(r"\d\d:\d\d:\d\d", t) for t in ticks), ticks
            assert len(set(ticks)) == len(ticks), ticks  # no label twice
            x, y = browser.evaluate(
                "(() => { const u = statusCharts()[0], r = u.over.getBoundingClientRect();"
                " return [r.right - 5, r.top + r.height / 2]; })()")
            browser.call("Input.dispatchMouseEvent", type="mouseMoved", x=x, y=y)
            readout = wait_for(lambda: (lambda v: v if v and v[0] != "\u2013" else None)(
                browser.evaluate("Array.from(document.querySelectorAll('#pos .u-legend "
                                 ".u-value')).map(e => e.textContent)")), 30,
                "no cursor readout under the position chart")
            assert re.fullmatch(r"\d\d:\d\d:\d\d", readout[0]), readout
            assert float(readout[2]) > 0 and readout[3] == "\u2013", readout  # axis 3: none
        finally:
            send(psi, ["2S00=8"], timeout=30)
        errors = browser.console_errors()
        assert errors == [], errors
    finally:
        browser.close()
    target = os.environ.get("STATUS_PAGE_SCREENSHOT")
    if target:
        shutil.copyfile(shot, target)
