"""The status page offers its history as CSV (issue 34): ``GET /api/history.csv``.

Pure: the CSV of a history body, cell by cell. Over loopback: the bridge's page
links it, and it holds the very samples of ``/api/history``, numbers unchanged.
"""
from __future__ import annotations

import csv
import io
import json
from typing import Iterator

import pytest

from tcp_bridge.status.history_csv import CONTENT_TYPE, history_csv
from tests.helpers import wait_until
from tests.test_bridge_http import Bridge

BODY = {"axes": [1, 4], "period": 0.5, "samples": [
    {"t": 1700000000.0, "position": [0.0, -2.5], "velocity": [0.0, None]},
    {"t": 1700000000.5004, "position": [1.25, None], "velocity": [3.3333333333333, 12.0]},
]}


def test_history_as_csv_cell_by_cell() -> None:
    text = history_csv(BODY)
    assert text.splitlines(keepends=True)[0].endswith("\r\n")  # RFC 4180 line ends
    assert list(csv.reader(io.StringIO(text))) == [
        ["time [s]", "axis 1 position [user units]", "axis 1 velocity [user units/s]",
         "axis 4 position [user units]", "axis 4 velocity [user units/s]"],
        ["1700000000.000", "0", "0", "-2.5", ""],
        ["1700000000.500", "1.25", "3.3333333333333", "", "12"],
    ]


def test_an_empty_history_is_its_header() -> None:
    assert history_csv({"axes": [], "samples": []}) == "time [s]\r\n"
    assert history_csv({"axes": [2], "samples": []}).count("\r\n") == 1


@pytest.fixture(scope="module")
def bridge() -> Iterator[Bridge]:
    b = Bridge()
    yield b
    b.close()


def test_the_page_offers_the_csv_and_it_holds_the_history(bridge: Bridge) -> None:
    status, _, page = bridge.get("/")
    assert status == 200 and b'href="/api/history.csv"' in page
    wait_until(lambda: len(json.loads(bridge.get("/api/history")[2])["samples"]) >= 3,
               why="no history")
    status, headers, body = bridge.get("/api/history.csv")
    assert status == 200 and headers["Content-Type"] == CONTENT_TYPE
    assert headers["Content-Disposition"] == 'attachment; filename="tcp-bridge-history.csv"'
    history = json.loads(bridge.get("/api/history")[2])
    rows = list(csv.reader(io.StringIO(body.decode("utf-8"))))
    assert rows[0][0] == "time [s]" and len(rows[0]) == 1 + 2 * len(history["axes"])
    by_time = {f"{s['t']:.3f}": s for s in history["samples"]}
    common = [r for r in rows[1:] if r[0] in by_time]
    assert len(common) >= 2  # the two GETs share most of the last minute
    for row in common:
        sample = by_time[row[0]]
        for k in range(len(history["axes"])):
            assert float(row[1 + 2 * k]) == sample["position"][k]
            assert float(row[2 + 2 * k]) == sample["velocity"][k]
