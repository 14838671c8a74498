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
     "'serve', 'check', 'record', 'send') (see tcp-bridge --help)"),
])
def test_a_misspelt_command_suggests_the_nearest(main: object, argv: List[str], line: str,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    assert run(main, argv, capsys) == (2, line + "\n")


def test_send_to_the_status_page_port_says_it_is_http(capsys: pytest.CaptureFixture[str]) -> None:
    """`tcp-bridge send 127.0.0.1:8080 1R10` to the --http port said only `connection
    closed after 0 bytes`, after the page's 10 s head timeout."""
    import asyncio
    import threading

    from tcp_bridge.status.http import StatusServer

    class NoSampler:
        latest = None

        async def close(self) -> None:
            pass

    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, daemon=True)
    thread.start()
    server = asyncio.run_coroutine_threadsafe(
        StatusServer(NoSampler(), "127.0.0.1", 0).start(), loop).result(30)  # type: ignore[arg-type]
    try:
        host, port = server.addresses[0]
        code, err = run(tcp_bridge, ["send", f"{host}:{port}", "1R10", "--timeout", "30"], capsys)
    finally:
        asyncio.run_coroutine_threadsafe(server.close(), loop).result(30)
        loop.call_soon_threadsafe(loop.stop)
        thread.join(5)
        loop.close()
    assert (code, err) == (2, f"tcp-bridge: {host}:{port}: it answered in HTTP: that is a web "
                              "server (the bridge's --http status page?), not a PSI port; the "
                              "bridge serves PSI on 1912 and 1913 (serve --port)\n")


def test_check_calls_silent_only_what_serve_would_not_serve(tmp_path: Path) -> None:
    """An EPOS4 that answers in 0.3 s: serve (0.5 s per request) serves it; check probed
    for 0.2 s and called it "device silent". Now both wait the bus's `timeout`."""
    import json
    import subprocess
    import sys

    from epos_link.simulator.core import Epos4Simulator
    from epos_link.simulator.link import LinkOptions, TcpLink
    from tests.test_cli_scan import Listening

    sim = Epos4Simulator(1, [2])
    link = TcpLink(Listening(sim), LinkOptions(delay=0.3)).start()
    config = tmp_path / "axes.toml"
    config.write_text(f'[bridge]\nstate_file = "{tmp_path / "state.json"}"\n'
                      f'[bus.can1]\nbackend = "epos"\nurl = "{link.url}"\ntimeout = 1.0\n'
                      '[[axis]]\nnode_id = 1\n')
    try:
        out = subprocess.run([sys.executable, "-m", "tcp_bridge.cli", "check", "--config",
                              str(config), "--json"], capture_output=True, text=True,
                             timeout=120)
    finally:
        link.close()
        sim.close()
    verdicts = [json.loads(line)["verdict"] for line in out.stdout.splitlines()]
    assert verdicts == ["found"], out.stdout + out.stderr


@pytest.mark.parametrize("verbose, shown", [(0, False), (1, False), (2, True)])
def test_python_cans_socketcand_chatter_stays_out_of_the_bridge_log(
        verbose: int, shown: bool, caplog: pytest.LogCaptureFixture) -> None:
    import logging

    from tcp_bridge.cli import configure_logging

    chatter = logging.getLogger("can.interfaces.socketcand")
    try:
        configure_logging(verbose)
        with caplog.at_level(logging.NOTSET):
            chatter.warning("Could not parse ascii message: < hi >")
            chatter.error("Failed to receive: timed out")
            logging.getLogger("tcp_bridge.bus.failfast").warning("bus can1: silent")
    finally:
        chatter.setLevel(logging.NOTSET)
        logging.getLogger("canopen").setLevel(logging.NOTSET)
    names = [r.name for r in caplog.records]
    assert ("can.interfaces.socketcand" in names) is shown
    assert "tcp_bridge.bus.failfast" in names  # the bridge's own line is always there
