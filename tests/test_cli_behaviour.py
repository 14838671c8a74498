"""The command-line findings of issue 13, each met the way a user meets it.

``--version``; arguments checked with one line and exit 2; ``tcp-bridge send``
with CR/LF inside a request; messages that name the port or URL once; help in
plain text; canopen's log lines quiet unless ``-v``; a busy serial port or USB
device named; ``epos-link sim`` node ids, serial numbers and a second TCP host.
"""
from __future__ import annotations

import argparse
import errno
import os
import socket
import subprocess
import sys
from importlib import metadata
from pathlib import Path
from typing import Iterator, List

import pytest
import serial
import usb.core

from epos_link import cli as epos_cli
from epos_link.client import EposClient
from epos_link.errors import TransportError
from epos_link.simulator.core import Epos4Simulator
from epos_link.simulator.link import TcpLink
from epos_link.transports import usb as usb_transport
from epos_link.transports.serial import open_serial
from epos_link.transports.usb import open_usb
from tcp_bridge import cli as bridge_cli
from tests.test_bridge_server import Running, make_engine
from tests.test_transport_usb import SCRIPT, FakeDevice, Finder

VERSION = metadata.version("epos-link")


def run(*args: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, *args], capture_output=True, text=True,
                          timeout=timeout)


def one_line_exit_2(out: subprocess.CompletedProcess[str]) -> str:
    """The stderr of a refused command line: exit 2, no traceback, one message line."""
    assert out.returncode == 2, out.stdout + out.stderr
    assert "Traceback" not in out.stderr
    lines = out.stderr.splitlines()
    assert len(lines) == 1, out.stderr
    return lines[0]


# -- --version -----------------------------------------------------------------------------


@pytest.mark.parametrize("main, prog", [(epos_cli.main, "epos-link"),
                                        (bridge_cli.main, "tcp-bridge")])
def test_version(main: object, prog: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as done:
        main(["--version"])  # type: ignore[operator]
    assert done.value.code == 0
    assert capsys.readouterr().out.split()[:2] == [prog, VERSION]


def test_license_matches_pyproject() -> None:
    root = Path(__file__).resolve().parent.parent
    assert (root / "LICENSE").read_text().startswith("MIT License\n")
    assert 'license = { text = "MIT" }' in (root / "pyproject.toml").read_text()


# -- help in plain text --------------------------------------------------------------------


def helps(parser: argparse.ArgumentParser) -> Iterator[str]:
    yield parser.format_help()
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                yield from helps(sub)


@pytest.mark.parametrize("parser", [epos_cli.build_parser, bridge_cli.parser])
def test_help_texts_are_plain_text(parser: object) -> None:
    texts = list(helps(parser()))  # type: ignore[operator]
    assert len(texts) > 3
    for text in texts:
        for markup in ("``", ":mod:", ":class:", ":func:", ":meth:"):
            assert markup not in text, text


# -- tcp-bridge send -------------------------------------------------------------------------


@pytest.mark.parametrize("args, words", [
    (["--timeout", "0"], "not a positive number of seconds"),
    (["--timeout", "-1"], "not a positive number of seconds"),
    (["--timeout", "nan"], "not a positive number of seconds"),
    (["--timeout", "inf"], "not a positive number of seconds"),
    (["--timeout", "soon"], "not a positive number of seconds"),
])
def test_send_refuses_a_bad_timeout(args: List[str], words: str) -> None:
    line = one_line_exit_2(run("-m", "tcp_bridge.cli", "send", *args, "127.0.0.1:1912", "1R10"))
    assert words in line


@pytest.mark.parametrize("address, words", [
    ("127.0.0.1:99999", "port 99999 is not 1..65535"),
    ("127.0.0.1:0", "port 0 is not 1..65535"),
    ("127.0.0.1", "expected HOST:PORT"),
    ("127.0.0.1:http", "expected HOST:PORT"),
])
def test_send_refuses_a_bad_port(address: str, words: str) -> None:
    line = one_line_exit_2(run("-m", "tcp_bridge.cli", "send", address, "1R10"))
    assert words in line


@pytest.fixture
def bridge() -> Iterator[Running]:
    running = Running(make_engine())
    yield running
    running.stop()
    running.engine.close()


def test_send_embedded_cr_or_lf_is_several_requests(bridge: Running,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    host, port = bridge.addresses[0][:2]
    code = bridge_cli.main(["send", f"{host}:{port}", "1R99\n2R91\r3R99\r\n", "2R99"])
    lines = capsys.readouterr().out.splitlines()
    assert code == 0
    assert lines == [f"1 R 99={bridge.engine.version} ACK", "2 R 91=0 ACK",
                     f"3 R 99={bridge.engine.version} ACK", f"2 R 99={bridge.engine.version} ACK"]


def test_send_refuses_a_request_that_is_not_ascii(capsys: pytest.CaptureFixture[str]) -> None:
    assert bridge_cli.main(["send", "127.0.0.1:1", "1R10\u00e9"]) == 2
    err = capsys.readouterr().err
    assert "is not ASCII" in err and err.count("\n") == 1


def test_send_of_nothing_is_refused(capsys: pytest.CaptureFixture[str]) -> None:
    assert bridge_cli.main(["send", "127.0.0.1:1", "\r\n"]) == 2
    assert "no request to send" in capsys.readouterr().err


# -- messages that name the port or URL once --------------------------------------------------


def test_a_missing_serial_port_is_named_once(tmp_path: Path) -> None:
    missing = str(tmp_path / "ttyACM9")
    line = one_line_exit_2(run("-m", "epos_link", "read", missing, "1", "0x1008", "0"))
    assert line.count(missing) == 1 and "No such file or directory" in line
    assert "did you mean" not in line  # a device path is not taken for HOST:PORT


@pytest.mark.parametrize("command", [["read", "{url}", "2", "0x6041"],
                                     ["watch", "{url}", "--node", "2", "--once"],
                                     ["record", "{url}", "--node", "2", "0x6041", "--csv", "-"]])
def test_host_port_without_a_scheme_hints_at_socket(command: List[str]) -> None:
    """127.0.0.1:PORT is opened as a device path (pyserial's rule for a URL without a
    scheme); every command's one line says what was probably meant."""
    url = "127.0.0.1:24571"
    line = one_line_exit_2(run("-m", "epos_link", *(w.format(url=url) for w in command)))
    assert line.endswith(f"cannot open {url}: No such file or directory "
                         f"(did you mean socket://{url}?)"), line


def test_an_unreachable_socket_is_named_once() -> None:
    line = one_line_exit_2(run("-m", "epos_link", "read", "socket://127.0.0.1:1", "1", "0x1008", "0"))
    assert line.count("127.0.0.1:1") == 1 and "Connection refused" in line


def test_the_bridge_names_an_epos_bus_url_once(tmp_path: Path) -> None:
    """A port that is not there does not stop the bridge (issue 24 point 2,
    tests/test_bridge_late_bus.py): one log line names the bus and the URL once."""
    import signal

    missing = str(tmp_path / "ttyACM9")
    config = tmp_path / "axes.toml"
    config.write_text(f'[bus.can1]\nbackend = "epos"\nurl = "{missing}"\n[[axis]]\nnode_id = 1\n')
    proc = subprocess.Popen([sys.executable, "-m", "tcp_bridge.cli", "serve", "--config", str(config),
                             "--port", "0", "--maintenance-port", "-1",
                             "--state-file", str(tmp_path / "state.toml")],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert "listening on" in proc.stdout.readline()  # type: ignore[union-attr]
        line = proc.stderr.readline()  # type: ignore[union-attr]
        proc.send_signal(signal.SIGINT)
        proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert line.count(missing) == 1 and "bus can1: cannot open" in line, line


def test_a_busy_serial_port_is_named() -> None:
    master, slave = os.openpty()
    path = os.ttyname(slave)
    try:
        holder = serial.Serial(path, exclusive=True)  # another program has the port
        try:
            with pytest.raises(TransportError) as info:
                open_serial(path)
            text = str(info.value)
            assert text.count(path) == 1 and "busy" in text and "another program" in text
        finally:
            holder.close()
        open_serial(path).close()  # free again
    finally:
        os.close(master)
        os.close(slave)


def test_a_busy_usb_device_is_named(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(usb_transport, "list_ftdi_ports", lambda: [])
    dev = FakeDevice(SCRIPT, serial="A1")

    def claimed_elsewhere(device: object, interface: int) -> None:
        raise usb.core.USBError("Resource busy", -6, errno.EBUSY)
    monkeypatch.setattr(dev._ctx, "managed_claim_interface", claimed_elsewhere)
    with pytest.raises(TransportError) as info:
        open_usb("usb://?serial=A1", find=Finder(dev), backend=object())
    text = str(info.value)
    assert text.count("usb://?serial=A1") == 1 and "busy" in text


def test_sim_trace_that_cannot_be_written_is_named_once(tmp_path: Path) -> None:
    path = str(tmp_path / "missing-dir" / "trace.txt")
    line = one_line_exit_2(run("-m", "epos_link", "sim", "--tcp", "127.0.0.1:0", "--trace", path))
    assert line.count(path) == 1 and "No such file or directory" in line


def test_sim_port_in_use_is_named_once() -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        line = one_line_exit_2(run("-m", "epos_link", "sim", "--tcp", f"127.0.0.1:{port}"))
    assert line.count(str(port)) == 1 and "Address already in use" in line


# -- canopen's log lines ---------------------------------------------------------------------


def test_canopen_log_lines_only_with_vv(tmp_path: Path) -> None:
    """An absent node on a CAN bus answers NAK; canopen's "Transfer aborted" line
    appears only with -vv: -v shows the bridge's own lines."""
    config = tmp_path / "axes.toml"
    config.write_text('[bus.can1]\nbackend = "canopen"\ninterface = "virtual"\n'
                      f'channel = "quiet-{os.getpid()}"\nsdo_timeout = 0.05\n'
                      '[[axis]]\ndevice = 2\nnode_id = 5\n')
    stderr = {}
    for extra in ([], ["-v"], ["-vv"]):
        proc = subprocess.Popen([sys.executable, "-m", "tcp_bridge.cli", "serve", "--config",
                                 str(config), "--port", "0", "--maintenance-port", "-1", *extra],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            line = proc.stdout.readline()  # type: ignore[union-attr]
            address = line.split("listening on ")[1].split(" ")[0]
            [reply] = bridge_cli.send(address, ["1R10"], timeout=10)
            assert reply.status.name == "NAK"
        finally:
            proc.send_signal(2)
            _, stderr[" ".join(extra)] = proc.communicate(timeout=30)
    assert "Transfer aborted" not in stderr[""]
    assert "Transfer aborted" not in stderr["-v"] and "canopen" not in stderr["-v"]
    assert "Transfer aborted" in stderr["-vv"]  # the line exists: the quieter runs hid it


def test_serve_v_shows_the_bridges_own_lines(tmp_path: Path) -> None:
    """serve --simulate -v: the bridge's start-up lines, none of canopen's (the simulated
    drives' SDO server logs every upload at INFO); -vv shows those too."""
    err = {}
    for flag in ("-v", "-vv"):
        proc = subprocess.Popen([sys.executable, "-m", "tcp_bridge.cli", "serve", "--simulate",
                                 "--port", "0", "--maintenance-port", "-1", "--state-file",
                                 str(tmp_path / "state.json"), flag],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            line = proc.stdout.readline()  # type: ignore[union-attr]
            address = line.split("listening on ")[1].split(" ")[0]
            [reply] = bridge_cli.send(address, ["2R10"], timeout=10)
            assert reply.status.name == "ACK"
        finally:
            proc.send_signal(2)
            _, err[flag] = proc.communicate(timeout=30)
    assert "tcp_bridge." in err["-v"] and "canopen" not in err["-v"], err["-v"]
    assert "canopen.sdo.server" in err["-vv"]


# -- epos-link sim -----------------------------------------------------------------------------


@pytest.mark.parametrize("args, words", [
    (["--drives", "1"], "1 is the simulated EPOS4's own node id"),
    (["--node-id", "3", "--drives", "2,3"], "3 is the simulated EPOS4's own node id"),
    (["--drives", "2,3,2"], "node id 2 appears twice"),
])
def test_sim_refuses_unusable_node_ids(args: List[str], words: str) -> None:
    line = one_line_exit_2(run("-m", "epos_link", "sim", "--tcp", "127.0.0.1:0", *args))
    assert words in line


def test_each_simulated_node_has_its_own_serial_number() -> None:
    with Epos4Simulator(1, [2, 3]) as sim:
        serials = [int.from_bytes(sim.drives[n].store.read(0x1018, 4), "little")
                   for n in (1, 2, 3)]
        names = {sim.drives[n].store.read(0x1008, 0) for n in (1, 2, 3)}
    assert len(set(serials)) == 3
    assert names == {b"EPOS4"}  # the product name, the same on every unit as on real ones


def test_a_second_host_of_sim_tcp_is_refused_with_a_message() -> None:
    with Epos4Simulator(1, []) as sim:
        link = TcpLink(sim).start()
        first = EposClient.open(link.url, timeout=0.5)
        try:
            assert first.read_object(1, 0x2000, 0)[0] == 1
            with socket.create_connection((link.host, link.port), timeout=5) as other:
                other.settimeout(5)
                received = b""
                while True:
                    chunk = other.recv(256)
                    if not chunk:
                        break
                    received += chunk
            assert received == TcpLink.BUSY_MESSAGE
            assert b"one host at a time" in received
            second = EposClient.open(link.url, timeout=0.2, retries=0)
            try:
                with pytest.raises(TransportError, match="another program"):
                    second.read_object(1, 0x2000, 0)
            finally:
                second.close()
            assert first.read_object(1, 0x2000, 0)[0] == 1  # the first host is still served
        finally:
            first.close()
            link.close()


@pytest.mark.parametrize("code, words", [
    (errno.ENODEV, "ip -details link show"),
    (errno.EAFNOSUPPORT, "modprobe can_raw"),
    (errno.ENETDOWN, "sudo ip link set can7 up type can bitrate 500000"),
])
def test_socketcan_failures_say_what_to_do(code: int, words: str) -> None:
    """python-can's SocketCAN errors are OSErrors; the bridge adds the usual remedy."""
    from tcp_bridge.backends.canopen_bus import _reason

    text = _reason(OSError(code, os.strerror(code)), "can7")
    assert text.startswith(os.strerror(code)) and words in text
    assert _reason(ValueError("bad bitrate"), "can7") == "bad bitrate"
