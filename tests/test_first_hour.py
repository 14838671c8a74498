"""The first hour's rough edges (issue 34 item 7), each as the user met it: the command
they typed and the one line they should have read instead. In-process ``main()`` calls
where the command allows it (fast), real sockets where the problem is a socket."""
from __future__ import annotations

import socket
from pathlib import Path
from typing import List

import pytest

from epos_link.cli import main as epos_link
from tcp_bridge.cli import main as tcp_bridge


def run(main: object, argv: List[str], capsys: pytest.CaptureFixture[str]) -> "tuple[int, str]":
    try:
        code = main(argv)  # type: ignore[operator]
    except SystemExit as exc:  # argparse's exit
        code = int(exc.code or 0)
    err = capsys.readouterr().err
    return code, err


EPSO = """
[bus.can1]
backend = "epso"
url = "/dev/ttyACM0"

[[axis]]
addr = 1
device = "maxon_epos4"
node_id = 1
position_factor = 1000
increments_per_revolution = 2000
"""


def test_a_misspelt_backend_names_file_table_and_the_nearest_backend_and_check_exits_2(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    table = tmp_path / "axes.toml"
    table.write_text(EPSO)
    line = (f"{table}: [bus.can1]: backend: unknown backend 'epso' (did you mean 'epos'?); "
            "known: canopen, epos, ethercat, instant, sim")
    code, err = run(tcp_bridge, ["check", "--config", str(table)], capsys)
    assert (code, err) == (2, f"tcp-bridge check: {line}\n")  # was rc 1 and a table row
    code, err = run(tcp_bridge, ["serve", "--config", str(table), "--port", "0"], capsys)
    assert (code, err) == (2, f"tcp-bridge: {line}\n")


@pytest.mark.parametrize("url", ["socket://localhost", "socket://localhost:", "socket://:4001",
                                 "socket://localhost:99999", "rfc2217://host"])
def test_a_socket_url_without_a_port_is_one_clear_line(
        url: str, capsys: pytest.CaptureFixture[str]) -> None:
    code, err = run(epos_link, ["read", url, "0", "0x1008"], capsys)
    scheme = url.split("://")[0]
    assert code == 2
    assert err == (f"epos-link read: link error: cannot open {url}: a {scheme}:// URL needs a "
                   f"host and a port 1..65535: {scheme}://HOST:PORT, e.g. "
                   f"{scheme}://localhost:4001\n")  # not pyserial's "'<=' not supported ..."


def test_monitor_on_a_busy_port_is_one_line_saying_what_to_do(
        capsys: pytest.CaptureFixture[str]) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        code, err = run(epos_link, ["monitor", "sim://", "--tcp", f"127.0.0.1:{port}"], capsys)
    assert code == 2
    assert err == (f"epos-link monitor: cannot listen on 127.0.0.1:{port}: Address already in "
                   "use; another program listens there: stop it, or choose another port "
                   "(port 0 picks a free one)\n")  # not "[Errno 98] ... (while attempting ...)"


def test_sim_without_drives_says_why_node_2_does_not_answer(
        capsys: pytest.CaptureFixture[str]) -> None:
    code, err = run(epos_link, ["read", "sim://", "2", "0x6041", "--timeout", "0.1",
                                "--retries", "0"], capsys)
    assert code == 1
    assert err == ("epos-link read: device error 0x05040000 SDO protocol timed out (ReadObject "
                   "node 2 0x6041/0x00); sim:// without ?drives= simulates the EPOS4 alone, "
                   "with no drive behind its gateway: give them, e.g. sim://?drives=2,3\n")
    # With drives, an absent node is the device's own answer, as on hardware: no hint.
    code, err = run(epos_link, ["read", "sim://?drives=2", "3", "0x6041", "--timeout", "0.1",
                                "--retries", "0"], capsys)
    assert code == 1 and "sim://" not in err and "0x05040000" in err


@pytest.mark.parametrize("main, argv, line", [
    (epos_link, ["reed", "sim://", "0", "0x1008"],
     "epos-link: argument COMMAND: invalid choice: 'reed' (did you mean 'read'? choose from "
     "'read', 'write', 'scan', 'nmt', 'monitor', 'decode', 'export', 'wireshark', 'backup', "
     "'restore', 'ports', 'record', 'watch', 'sim') (see epos-link --help)"),
    (tcp_bridge, ["sned", "127.0.0.1:1912", "1R10"],
     "tcp-bridge: argument command: invalid choice: 'sned' (did you mean 'send'? choose from "
     "'serve', 'check', 'send') (see tcp-bridge --help)"),
])
def test_a_misspelt_command_suggests_the_nearest(main: object, argv: List[str], line: str,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    assert run(main, argv, capsys) == (2, line + "\n")
