"""The status page in a real browser (issue 25): headless chromium over DevTools.

``tcp-bridge serve --simulate --http 127.0.0.1:0`` runs as a subprocess (the
command a user types); chromium loads the page; the test checks that every
configured axis has its row, that a moving axis's position cell follows the
move, and that the page logged no console error, no uncaught exception and no
failed load. Screenshots stay under the test's ``tmp_path`` (pytest keeps the
last runs). docs/status-page.png comes from tests/test_status_page_browser.py.

Skipped, with the reason shown, where no chromium is installed (Debian: ``apt
install chromium``).
"""
from __future__ import annotations

import re
import subprocess
import sys
import time
from pathlib import Path
from typing import Iterator, Tuple

import pytest

from tcp_bridge.cli import send
from tcp_bridge.wire import Status
from tests.cdp import Chromium, find_chromium

CHROMIUM = find_chromium()
pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="no chromium binary on PATH "
                                "(Debian: apt install chromium); the status page's browser "
                                "test cannot run")


def wait_for(what, timeout: float, why: str):  # type: ignore[no-untyped-def]
    """Poll ``what`` until it returns something true; bounds are far above the need."""
    deadline = time.monotonic() + timeout
    while True:
        value = what()
        if value:
            return value
        assert time.monotonic() < deadline, f"{why} (within {timeout} s)"
        time.sleep(0.1)


@pytest.fixture(scope="module")
def served() -> Iterator[Tuple[str, str]]:
    """(PSI HOST:PORT, page URL) of ``serve --simulate --axes 3 --http 127.0.0.1:0``."""
    proc = subprocess.Popen([sys.executable, "-m", "tcp_bridge.cli", "serve", "--simulate",
                             "--axes", "3", "--port", "0", "--maintenance-port", "-1",
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


def ok(psi: str, *requests: str) -> None:
    for reply in send(psi, requests, timeout=30):
        assert reply.status is Status.ACK, reply


def test_the_page_shows_every_axis_and_follows_a_move(served: Tuple[str, str],
                                                      tmp_path: Path) -> None:
    psi, url = served
    assert CHROMIUM is not None
    browser = Chromium(CHROMIUM, tmp_path / "profile")
    try:
        browser.call("Page.navigate", url=url)
        rows = wait_for(lambda: browser.evaluate(
            "Array.from(document.querySelectorAll('#rows tr')).map(tr => tr.id)"), 60,
            "the page shows no axis")
        assert rows == ["axis-1", "axis-2", "axis-3"]
        assert browser.evaluate("document.getElementById('state-2').textContent") \
            == "switch on disabled"
        browser.screenshot(tmp_path / "at-rest.png")

        position = "document.getElementById('pos-2').textContent"
        first = float(wait_for(lambda: browser.evaluate(position), 30, "no position"))
        ok(psi, "2S04=1", "2S05=5", "2S06=100", "2S02=300", "2S00=1")
        try:
            moved = wait_for(lambda: float(browser.evaluate(position)) > first + 0.5 and
                             float(browser.evaluate(position)), 60,
                             "the page's position of axis 2 does not follow the move")
            later = wait_for(lambda: float(browser.evaluate(position)) > moved and
                             float(browser.evaluate(position)), 60,
                             "the page's position stopped changing during the move")
            assert first < moved < later
            assert browser.evaluate("document.getElementById('state-2').textContent") \
                == "operation enabled"
            assert browser.evaluate("document.getElementById('reached-2').textContent") \
                == "no"
            assert browser.evaluate("document.getElementById('pos-1').textContent") == "0.000"
            # A few seconds of the move on the plot (more for the picture in docs/).
            time.sleep(2)
            shot = browser.screenshot(tmp_path / "moving.png")
        finally:
            ok(psi, "2S00=8")
        assert shot.stat().st_size > 1000
        errors = browser.console_errors()
        assert errors == [], errors
    finally:
        browser.close()
