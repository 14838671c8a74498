"""``epos-link record`` says what is wrong when a node's SDO channel is someone else's.

Issue 34, item 2: recording a node through the EPOS4's gateway while another program
(a bridge, a canopen script) reads the same node by SDO on the same CAN bus stopped
after some samples with a bare "SDO protocol timed out". Both are clients of the
node's one default SDO channel (CiA 301 7.2.4). The recorder now says so, and what
to do instead. Reproduced as a user meets it: ``epos-link sim`` with its CAN bus
served over socketcand, a canopen client polling node 2 through it, and ``record``.
"""
from __future__ import annotations

import re
import subprocess
import sys
import threading
from pathlib import Path

import canopen
import pytest

from epos_link.errors import DeviceError, EposTimeoutError
from epos_link.tools.record import channel_taken

ROOT = Path(__file__).resolve().parent.parent


def test_the_hint_names_the_channel_and_the_way_out() -> None:
    hint = channel_taken(DeviceError(0x05040000), 2, 10)
    assert hint is not None
    assert "node 2 answered 10 samples" in hint and "0x602/0x582" in hint
    assert "CiA 301 7.2.4" in hint and "tcp-bridge record HOST:PORT AXIS" in hint
    assert channel_taken(DeviceError(0x05030000), 5, 1) is not None  # toggle bit


@pytest.mark.parametrize("error, node, samples", [
    (DeviceError(0x05040000), 2, 0),   # never answered: an absent node, not a shared channel
    (DeviceError(0x05040000), 0, 10),  # the EPOS4 itself: no SDO
    (DeviceError(0x06020000), 2, 10),  # the node refused: its own answer
    (EposTimeoutError("silent link"), 2, 10),  # the link, not the gateway
])
def test_no_hint_where_it_would_mislead(error: Exception, node: int, samples: int) -> None:
    assert channel_taken(error, node, samples) is None  # type: ignore[arg-type]


def test_record_while_another_sdo_client_polls_the_node(tmp_path: Path) -> None:
    cli = [sys.executable, "-m", "epos_link"]
    sim = subprocess.Popen([*cli, "sim", "--tcp", "127.0.0.1:0", "--drives", "2",
                            "--can-server", "127.0.0.1:0"], cwd=ROOT, stdout=subprocess.PIPE,
                           text=True)
    network = canopen.Network()
    stop = threading.Event()
    try:
        assert sim.stdout is not None
        url = re.search(r"socket://\S+", sim.stdout.readline())
        assert url is not None
        can = None
        while can is None:
            can = re.search(r"socketcand at (\S+):(\d+)", sim.stdout.readline())
        network.connect(interface="socketcand", host=can.group(1), port=int(can.group(2)),
                        channel="can0")
        other = network.add_node(2, canopen.ObjectDictionary())

        def poll() -> None:  # the other program: reads node 2 by SDO, over and over
            while not stop.is_set():
                try:
                    other.sdo.upload(0x6064, 0)
                except Exception:  # its own transfers suffer too; it goes on
                    pass

        record = subprocess.Popen([*cli, "record", url.group(0), "--node", "2",
                                   "position_actual_value", "statusword", "--duration", "30",
                                   "--csv", str(tmp_path / "x.csv")],
                                  cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                  text=True)
        assert record.stderr is not None
        # The node has answered (the first sample, "now"): then the other program starts.
        assert record.stderr.readline().startswith("triggered; recording")
        poller = threading.Thread(target=poll, daemon=True)
        poller.start()
        out, err = record.communicate(timeout=120)
    finally:
        stop.set()
        network.disconnect()
        sim.terminate()
        sim.wait(timeout=30)
    assert record.returncode == 1, err
    assert "stopped by an error" in out
    lines = err.strip().splitlines()
    assert re.match(r"epos-link record: device error 0x0(504000[013]|5030000) ", lines[-2]), lines
    assert re.match(r"epos-link record: node 2 answered \d+ samples, then its SDO transfer "
                    r"failed .*another SDO client of node 2.*0x602/0x582.*"
                    r"tcp-bridge record HOST:PORT AXIS", lines[-1]), lines[-1]
    assert (tmp_path / "x.csv").exists()  # what came before is kept
