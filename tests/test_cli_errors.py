"""A bad argument is one line and exit 2 in every console script; a port that cannot be
opened is one line, exit 2, before ``serve`` says it is listening.

Met as a user meets them: through each tool's ``main()`` (stderr captured) or, for
``serve``, a subprocess that must exit by itself.
"""
from __future__ import annotations

import argparse
import socket
import subprocess
import sys
import threading
import tomllib
from pathlib import Path
from typing import Callable, Iterator, List

import pytest

from epos_link import cli as epos_cli
from epos_link.cli_parser import OneLineParser
from tcp_bridge import cli as bridge_cli
from tcp_bridge.client import parse_address

ROOT = Path(__file__).resolve().parent.parent
# Each console script of pyproject.toml and the function that builds its parser.
PARSERS: dict[str, Callable[[], argparse.ArgumentParser]] = {
    "epos-link": epos_cli.build_parser,
    "tcp-bridge": bridge_cli.parser,
}
MAINS = {"epos-link": epos_cli.main, "tcp-bridge": bridge_cli.main}


def parsers(parser: argparse.ArgumentParser) -> Iterator[argparse.ArgumentParser]:
    yield parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                yield from parsers(sub)


def test_every_console_script_parser_is_one_line() -> None:
    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    assert set(scripts) == set(PARSERS), "a new console script: add its parser here"
    for name, build in PARSERS.items():
        found = list(parsers(build()))
        assert len(found) > 3, name
        for p in found:
            assert isinstance(p, OneLineParser), p.prog


def refused(tool: str, argv: List[str], capsys: pytest.CaptureFixture[str]) -> str:
    """stderr of a refused command line, checked to be one line with exit status 2."""
    with pytest.raises(SystemExit) as done:
        MAINS[tool](argv)
    assert done.value.code == 2
    out, err = capsys.readouterr()
    assert out == "" and err.endswith("\n") and err.count("\n") == 1, err
    return err.rstrip("\n")


@pytest.mark.parametrize("tool, argv, line", [
    ("tcp-bridge", ["serve", "--simulate", "--http", "abc"],
     "tcp-bridge serve: argument --http: 'abc' is not HOST:PORT (port 0..65535; 0 picks one) "
     "(see tcp-bridge serve --help)"),
    ("tcp-bridge", ["serve", "--simulate", "--http", "127.0.0.1:99999"],
     "tcp-bridge serve: argument --http: '127.0.0.1:99999' is not HOST:PORT (port 0..65535; 0 "
     "picks one) (see tcp-bridge serve --help)"),
    ("tcp-bridge", ["serve", "--simulate", "--allow", "notacidr"],
     "tcp-bridge serve: argument --allow: 'notacidr' is not a network in CIDR notation "
     "('notacidr' does not appear to be an IPv4 or IPv6 network) (see tcp-bridge serve --help)"),
    ("tcp-bridge", ["send", "localhost", "1R10"],
     "tcp-bridge send: argument HOST:PORT: expected HOST:PORT, not 'localhost' "
     "(see tcp-bridge send --help)"),
    ("tcp-bridge", ["check", "--simulate", "--axes", "x"],
     "tcp-bridge check: argument --axes: 'x' is not a number of axes "
     "(see tcp-bridge check --help)"),
    ("tcp-bridge", [], "tcp-bridge: the following arguments are required: command "
     "(see tcp-bridge --help)"),
    ("epos-link", ["watch", "sim://", "--period", "0"],
     "epos-link watch: argument --period: must be above 0 (see epos-link watch --help)"),
    ("epos-link", ["read", "sim://", "200", "statusword"],
     "epos-link read: argument NODE: node ids are 0..127, got 200 (see epos-link read --help)"),
    ("epos-link", ["read", "sim://", "1", "statusword", "--type", "q"],
     "epos-link read: argument --type: invalid choice: 'q' (choose from 'bool', 'i8', 'i16', "
     "'i32', 'i64', 'u8', 'u16', 'u32', 'u64', 'f32', 'f64', 'str', 'ustr', 'bytes', "
     "'domain') (see epos-link read --help)"),
    ("epos-link", ["read", "sim://", "1"],
     "epos-link read: the following arguments are required: INDEX|NAME "
     "(see epos-link read --help)"),
    ("epos-link", ["nosuch"],
     "epos-link: argument COMMAND: invalid choice: 'nosuch' (choose from 'read', 'write', "
     "'scan', 'nmt', 'monitor', 'decode', 'export', 'wireshark', 'backup', 'restore', "
     "'ports', 'record', 'watch', 'sim') (see epos-link --help)"),
])
def test_a_bad_argument_is_one_line(tool: str, argv: List[str], line: str,
                                    capsys: pytest.CaptureFixture[str]) -> None:
    assert refused(tool, argv, capsys) == line


@pytest.mark.parametrize("tool, argv, line", [
    # argparse finds them after the subcommand parsed, from the top-level parser: the
    # line still names the subcommand they were given to.
    ("epos-link", ["read", "sim://", "1", "0x6041", "0", "extra"],
     "epos-link read: unrecognized arguments: extra (see epos-link read --help)"),
    ("epos-link", ["watch", "sim://", "--bogus"],
     "epos-link watch: unrecognized arguments: --bogus (see epos-link watch --help)"),
    ("tcp-bridge", ["send", "127.0.0.1:1912", "1R10", "--bogus"],
     "tcp-bridge send: unrecognized arguments: --bogus (see tcp-bridge send --help)"),
])
def test_unrecognized_arguments_name_their_subcommand(tool: str, argv: List[str], line: str,
                                                      capsys: pytest.CaptureFixture[str]
                                                      ) -> None:
    assert refused(tool, argv, capsys) == line


@pytest.mark.parametrize("tool, argv", [("epos-link", ["read", "--help"]),
                                        ("tcp-bridge", ["serve", "--help"]),
                                        ("tcp-bridge", ["--help"])])
def test_help_is_argparse_help(tool: str, argv: List[str],
                               capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as done:
        MAINS[tool](argv)
    assert done.value.code == 0
    out, err = capsys.readouterr()
    prog = " ".join([tool, *argv[:-1]])
    assert err == "" and out.startswith(f"usage: {prog} [-h]") and "\noptions:\n" in out
    assert out == next(p for p in parsers(PARSERS[tool]()) if p.prog == prog).format_help()


# -- HOST:PORT given a URL -------------------------------------------------------------------


@pytest.mark.parametrize("argv, line", [
    (["send", "http://127.0.0.1:24117", "1R10"],
     "tcp-bridge send: argument HOST:PORT: expected HOST:PORT, not a URL "
     "(did you mean 127.0.0.1:24117?) (see tcp-bridge send --help)"),
    (["send", "socket://localhost:1912", "1R10"],
     "tcp-bridge send: argument HOST:PORT: expected HOST:PORT, not a URL "
     "(did you mean localhost:1912?) (see tcp-bridge send --help)"),
    (["send", "tcp://[::1]:1912", "1R10"],
     "tcp-bridge send: argument HOST:PORT: expected HOST:PORT, not a URL "
     "(did you mean [::1]:1912?) (see tcp-bridge send --help)"),
    (["send", "tcp://localhost", "1R10"],  # no port: nothing to suggest
     "tcp-bridge send: argument HOST:PORT: expected HOST:PORT, not a URL "
     "(see tcp-bridge send --help)"),
    (["serve", "--simulate", "--http", "http://127.0.0.1:8080"],
     "tcp-bridge serve: argument --http: expected HOST:PORT, not a URL "
     "(did you mean 127.0.0.1:8080?) (see tcp-bridge serve --help)"),
    (["serve", "--simulate", "--can-server", "socket://127.0.0.1:0"],
     "tcp-bridge serve: argument --can-server: expected HOST:PORT, not a URL "
     "(did you mean 127.0.0.1:0?) (see tcp-bridge serve --help)"),
])
def test_a_url_for_host_port_is_refused_with_a_suggestion(
        argv: List[str], line: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert refused("tcp-bridge", argv, capsys) == line


def test_send_refuses_a_url_without_resolving_it() -> None:
    with pytest.raises(ValueError, match=r"not a URL \(did you mean 10\.0\.0\.1:1912\?\)"):
        parse_address("tcp://10.0.0.1:1912")
    assert parse_address("localhost:1912") == ("localhost", 1912)


# -- serve: every socket opened before "listening on" ----------------------------------------


@pytest.fixture
def taken() -> Iterator[int]:
    """A port on 127.0.0.1 that another program listens on."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        yield s.getsockname()[1]


def serve(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "tcp_bridge.cli", "serve", "--simulate",
                           "--port", "0", *args], capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize("option, line", [
    ("--http", "tcp-bridge: --http: cannot listen on 127.0.0.1 port {port}: "
               "Address already in use"),
    ("--can-server", "tcp-bridge: bus can1: can_server: cannot listen on 127.0.0.1 port "
                     "{port}: Address already in use"),
    ("--maintenance-port", "tcp-bridge: cannot listen on 127.0.0.1 port 0/{port}: "
                           "Address already in use"),
])
def test_a_port_in_use_is_one_line_before_listening(taken: int, option: str,
                                                    line: str) -> None:
    value = str(taken) if option == "--maintenance-port" else f"127.0.0.1:{taken}"
    extra = [] if option == "--maintenance-port" else ["--maintenance-port", "-1"]
    out = serve(*extra, option, value)
    assert out.returncode == 2, out
    assert out.stdout == ""  # no "listening on": it was never true
    assert out.stderr == line.format(port=taken) + "\n"


def test_a_status_page_port_in_use_closes_the_buses(taken: int, monkeypatch: pytest.MonkeyPatch,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    from tcp_bridge.engine import Engine

    closed: List[Engine] = []
    close = Engine.close

    def recorded(self: Engine, wait: bool = True) -> None:
        closed.append(self)
        close(self, wait)

    monkeypatch.setattr(Engine, "close", recorded)
    before = set(threading.enumerate())
    code = bridge_cli.main(["serve", "--simulate", "--port", "0", "--maintenance-port", "-1",
                            "--http", f"127.0.0.1:{taken}"])
    assert code == 2
    out, err = capsys.readouterr()
    assert out == ""
    assert err == f"tcp-bridge: --http: cannot listen on 127.0.0.1 port {taken}: " \
                  "Address already in use\n"
    assert len(closed) == 1  # the engine, its bus workers and its simulated buses
    left = [t for t in set(threading.enumerate()) - before if t.is_alive() and not t.daemon]
    assert left == []
