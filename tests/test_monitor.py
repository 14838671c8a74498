"""``epos-link monitor`` in front of the simulator, driven by EposClient through it,
over real loopback sockets and a pseudo-terminal (issue 11, Must show 1)."""
from __future__ import annotations

import io
import json
import os
import select
import signal
import socket
import subprocess
import sys
import threading
from pathlib import Path
from typing import Iterator

import pytest

from epos_link.capture import CaptureWriter, Direction, read_capture
from epos_link.client import EposClient
from epos_link.errors import DeviceError, RemoteProtocolError
from epos_link.simulator.core import Epos4Simulator
from epos_link.simulator.link import TcpLink
from epos_link.tools.pcapng import FLAG_INBOUND, FLAG_OUTBOUND, read_pcapng

ANSWER = bytes.fromhex("90 02 00 04 00 00 00 00 01 90 90 00 00 9A 5C")  # guide Table 2-6
WAIT = 30.0  # generous bound for a loaded machine; never a timing assertion


class Monitor:
    """``epos-link monitor`` as a user runs it: a child process, stopped by SIGTERM."""

    def __init__(self, *args: str, env: "dict[str, str] | None" = None) -> None:
        self.proc = subprocess.Popen([sys.executable, "-m", "epos_link.cli", "monitor", *args],
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                     env={**os.environ, **(env or {})})
        listen_on = self.proc.stderr  # always: standard output may go to /dev/null
        assert listen_on is not None
        ready, _, _ = select.select([listen_on], [], [], WAIT)
        assert ready, "the monitor did not say where it listens"
        first = listen_on.readline().decode()
        assert first.startswith("listening on "), first + listen_on.read().decode()
        self.where = first.split("listening on ", 1)[1].strip()

    def stop(self) -> tuple[int, str, str, bytes]:
        self.proc.send_signal(signal.SIGTERM)
        out, err = self.proc.communicate(timeout=WAIT)
        return self.proc.returncode, out.decode(errors="replace"), err.decode(), out


@pytest.fixture()
def sim() -> Iterator[tuple[TcpLink, io.StringIO]]:
    """The simulator over TCP, node 1 with drive 2 behind its gateway; its own trace
    is the reference for what crossed the wire on its side."""
    trace = io.StringIO()
    simulator = Epos4Simulator(1, [2])
    link = TcpLink(simulator, trace=CaptureWriter(trace)).start()
    try:
        yield link, trace
    finally:
        link.close()
        simulator.close()


def conversation(client: EposClient) -> list[object]:
    """What an application does: reads, a write, a string, an error."""
    out: list[object] = [client.read_object(1, 0x6064, 0)]
    client.write_object(2, 0x6081, 0, (1234).to_bytes(4, "little"))
    out.append(client.read_object(2, 0x6081, 0))
    out.append(client.upload(1, 0x1008, 0))
    try:
        client.read_object(1, 0x5FFF, 0)
    except DeviceError as exc:
        out.append(exc.code)
    return out


def test_monitor_shows_named_values_and_records_a_replayable_capture(sim, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    link, sim_trace = sim
    record = tmp_path / "cap.txt"
    mon = Monitor(link.url, "--tcp", "127.0.0.1:0", "--record", str(record))
    assert mon.where.startswith("socket://127.0.0.1:")
    with EposClient.open(mon.where) as client:
        results = conversation(client)
    code, out, err, _ = mon.stop()
    assert code == 0, err
    assert results[1] == (1234).to_bytes(4, "little") and results[-1] == 0x06020000
    lines = out.splitlines()
    text = "\n".join(lines)
    # Names and values from the EDS (0x6081 Profile velocity, UNSIGNED32; 0x1008 VISIBLE_STRING).
    assert "TX WriteObject                    node 2 0x6081/0x00 Profile velocity = 1234 (0x000004D2) crc ok" in text
    assert "RX Answer(ReadObject)             node 2 0x6081/0x00 Profile velocity = 1234 (0x000004D2) ok crc ok " in text
    assert 'Manufacturer device name = "' in text
    assert "node 1 0x5FFF/0x00 error 0x06020000 Object does not exist error crc ok" in text
    assert "application connected from 127.0.0.1:" in text
    answers = [line for line in lines if " RX Answer(" in line]
    assert len(answers) == 5 and all(line.endswith(" ms") for line in answers)

    # Byte-exact: what the monitor recorded is what the simulator received and sent.
    captured = read_capture(record.read_text())
    reference = read_capture(sim_trace.getvalue())
    for d in Direction:
        assert captured.stream(d) == reference.stream(d)
    # ... and it replays: the same application run against replay:// gets the same answers.
    with EposClient.open(f"replay://{record}") as replayed:
        assert conversation(replayed) == results
        replayed.transport.check_complete()  # type: ignore[attr-defined]


def test_json_lines_and_time_modes(sim) -> None:  # type: ignore[no-untyped-def]
    link, _ = sim
    mon = Monitor(link.url, "--tcp", "127.0.0.1:0", "--json", "-t", "d")
    with EposClient.open(mon.where) as client:
        client.read_object(2, 0x6081, 0)
    code, out, err, _ = mon.stop()
    assert code == 0, err
    objs = [json.loads(line) for line in out.splitlines()]  # every line of standard output is JSON
    assert not [o for o in objs if "listening on" in str(o)]
    frames = [o for o in objs if "opcode" in o]
    assert [o["direction"] for o in frames] == ["TX", "RX"]
    assert frames[1]["object"] == "Profile velocity" and frames[1]["type"] == "u32"
    assert frames[1]["value"] == 1000 and frames[1]["answers"] == "ReadObject"
    assert frames[1]["latency_ms"] >= 0 and frames[1]["raw"].startswith("9002")
    assert all(o["time"] >= 0 for o in objs)  # deltas


class GarblingDevice:
    """A device on TCP that answers every request with junk, a frame with a bad CRC,
    a stuffing fault and then the guide's good answer (Table 2-6)."""

    REPLY = b"\xAA\xBB" + ANSWER[:-1] + b"\x00" + bytes.fromhex("90 02 00 04 90 41") + ANSWER

    def __init__(self) -> None:
        self.sock = socket.create_server(("127.0.0.1", 0))
        self.url = "socket://127.0.0.1:%d" % self.sock.getsockname()[1]
        self.thread = threading.Thread(target=self.serve, daemon=True)
        self.thread.start()

    def serve(self) -> None:
        conn, _ = self.sock.accept()
        with conn:
            conn.settimeout(WAIT)
            try:
                while conn.recv(4096):
                    conn.sendall(self.REPLY)
            except OSError:
                pass

    def close(self) -> None:
        self.sock.close()


def test_garbled_frames_are_shown_and_the_monitor_resyncs(tmp_path: Path) -> None:
    dev = GarblingDevice()
    try:
        mon = Monitor(dev.url, "--tcp", "127.0.0.1:0", "-x", "--pcapng", str(tmp_path / "g.pcapng"))
        with EposClient.open(mon.where, retries=0) as client:
            with pytest.raises(RemoteProtocolError):  # the client gives up at the bad CRC
                client.read_object(1, 0x30B0, 0)
        code, out, err, _ = mon.stop()
    finally:
        dev.close()
    assert code == 0, err
    rx = [line for line in out.splitlines() if " RX " in line]
    assert "not a frame: 2 bytes outside any frame [AA BB]" in rx[0]
    assert "CRC BAD" in rx[1] and rx[1].endswith("00 00 00 00 01 90 90 00 00 9A 00]")
    assert "not a frame: DLE followed by 0x41 inside a frame [90 02 00 04 90]" in rx[2]
    assert "not a frame: 1 bytes outside any frame [41]" in rx[3]
    assert "Answer" in rx[4] and "crc ok" in rx[4] and rx[4].endswith("[90 02 00 04 00 00 00 00 01 90 90 00 00 9A 5C]")
    # Every byte is in the pcapng as well, junk included.
    _, packets = read_pcapng((tmp_path / "g.pcapng").read_bytes())
    assert b"".join(p.data for p in packets if p.flags == FLAG_INBOUND) == GarblingDevice.REPLY


def test_pcapng_to_standard_output_and_lines_to_standard_error(sim) -> None:  # type: ignore[no-untyped-def]
    link, _ = sim
    mon = Monitor(link.url, "--tcp", "127.0.0.1:0", "--pcapng", "-")
    with EposClient.open(mon.where) as client:
        client.read_object(1, 0x6064, 0)
    code, _, err, raw = mon.stop()
    assert code == 0
    interfaces, packets = read_pcapng(raw)
    assert interfaces[0].linktype == 147
    assert [p.flags for p in packets] == [FLAG_OUTBOUND, FLAG_INBOUND]
    assert packets[0].data == bytes.fromhex("90 02 60 02 01 64 60 00 29 5A")  # ReadObject node 1 0x6064/0
    assert "TX ReadObject" in err and "Position actual value" in err


@pytest.mark.skipif(os.name != "posix", reason="pseudo-terminals are POSIX")
def test_pty_front(sim) -> None:  # type: ignore[no-untyped-def]
    link, _ = sim
    mon = Monitor(link.url, "--pty")
    assert mon.where.startswith("/dev/")
    with EposClient.open(mon.where) as client:
        assert client.read_object(2, 0x6081, 0) == (1000).to_bytes(4, "little")
    code, out, err, _ = mon.stop()
    assert code == 0, err
    assert "RX Answer(ReadObject)             node 2 0x6081/0x00 Profile velocity = 1000" in out


@pytest.mark.parametrize("args,message", [
    (["socket://127.0.0.1:1", "--tcp", "127.0.0.1:0"], "cannot open socket://127.0.0.1:1"),
    (["sim://", "--tcp", "127.0.0.1:0", "--eds", "/nonexistent.eds"], "no such file"),
    (["sim://", "--tcp", "nonsense"], "expected HOST:PORT"),
    (["sim://"], "one of the arguments --pty --tcp is required"),
])
def test_bad_arguments_are_one_line_and_exit_2(args: list[str], message: str) -> None:
    p = subprocess.run([sys.executable, "-m", "epos_link.cli", "monitor", *args],
                       capture_output=True, text=True, timeout=WAIT)
    assert p.returncode == 2 and message in p.stderr and "Traceback" not in p.stderr


def test_a_missing_device_is_named_once(tmp_path: Path) -> None:
    missing = str(tmp_path / "ttyUSB0")
    p = subprocess.run([sys.executable, "-m", "epos_link.cli", "monitor", missing, "--pty"],
                       capture_output=True, text=True, timeout=WAIT)
    assert p.returncode == 2
    assert p.stderr.count(missing) == 1, p.stderr
    assert p.stderr.startswith(f"epos-link monitor: cannot open {missing}"), p.stderr
