"""A spawned command imports what it runs and no more (issue 32): the suite and the
docs spawn ``tcp-bridge send`` and ``epos-link`` hundreds of times, and each import of
canopen and python-can, asyncio or importlib.metadata costs every spawn 0.1-0.3 s of
CPU. The parsers add a command's arguments only for that command
(``tcp_bridge.cli.parser``, ``epos_link.cli.build_parser``), ``--version`` looks the
version up only when asked, and serve's imports are serve's."""
from __future__ import annotations

import subprocess
import sys
from typing import List, Set

import pytest

HEAVY = {"asyncio", "canopen", "can", "importlib.metadata", "epos_link.tools.record",
         "epos_link.tools.access", "tcp_bridge.check", "tcp_bridge.record",
         "tcp_bridge.tables.axes"}


def heavy_imports(package: str, argv: List[str]) -> Set[str]:
    """The :data:`HEAVY` modules loaded once ``package.cli.main(argv)`` has returned, in
    a fresh interpreter (a refused connection or argparse's exit included); --version
    may use importlib.metadata, it is what it asks for."""
    code = ("import sys\n"
            f"from {package}.cli import main\n"
            "try:\n"
            f"    main({argv!r})\n"
            "except SystemExit:\n"
            "    pass\n"
            "print('MODULES', ' '.join(sorted(sys.modules)))\n")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    line = next(x for x in p.stdout.splitlines() if x.startswith("MODULES "))
    allowed = {"importlib.metadata"} if argv == ["--version"] else set()
    return set(line.split()[1:]) & (HEAVY - allowed)


@pytest.mark.parametrize("argv", [["send", "127.0.0.1:1", "1R10"], ["--version"], ["--help"],
                                  ["serve", "--help"]])
def test_tcp_bridge_imports_neither_canopen_nor_asyncio_for_send_help_or_version(
        argv: List[str]) -> None:
    assert heavy_imports("tcp_bridge", argv) == set()


def test_tcp_bridge_record_help_still_has_its_arguments() -> None:
    p = subprocess.run([sys.executable, "-m", "tcp_bridge.cli", "record", "--help"],
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == 0 and "--trigger WHEN" in p.stdout and "--csv FILE" in p.stdout


@pytest.mark.parametrize("argv", [["--version"], ["--help"], ["decode", "--help"]])
def test_epos_link_imports_no_canopen_for_help_or_version(argv: List[str]) -> None:
    assert heavy_imports("epos_link", argv) == set()
