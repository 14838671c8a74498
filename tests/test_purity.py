"""The sans-I/O modules import no I/O, clock or concurrency module (STYLE.md)."""
from __future__ import annotations

import subprocess
import sys

import pytest

PURE = [
    "epos_link.errors", "epos_link.codes", "epos_link.crc", "epos_link.framing",
    "epos_link.messages", "epos_link.capture", "epos_link.segmented", "epos_link.cia402",
    "epos_link.simulator.device", "epos_link.simulator.units", "epos_link.simulator.safety",
    "epos_link.simulator.faults", "epos_link.simulator.homing", "epos_link.simulator.nmt",
    "epos_link.simulator.clock", "epos_link.simulator.motion",
    "epos_link.simulator.socketcand_wire",
    "epos_link.simulator.ethercat.frame", "epos_link.simulator.ethercat.esc",
    "epos_link.simulator.ethercat.sii", "epos_link.simulator.ethercat.coe",
    "epos_link.simulator.ethercat.pdo", "epos_link.simulator.ethercat.slave",
    "epos_link.simulator.ethercat.segment",
    "epos_link.tools.decode", "epos_link.tools.pcapng",
    "tcp_bridge.wire", "tcp_bridge.wire.lines", "tcp_bridge.wire.requests",
    "tcp_bridge.wire.replies", "tcp_bridge.tables.commands", "tcp_bridge.tables.units",
    "tcp_bridge.access", "tcp_bridge.bus.health", "tcp_bridge.status.rows",
    "tcp_bridge.status.page", "tcp_bridge.status.slots", "tcp_bridge.backends.ethercat_pdo",
    "epos_link.data_recorder", "tcp_bridge.status.history_csv",
]
FORBIDDEN = ["serial", "usb", "socket", "asyncio", "threading", "time", "select", "can", "canopen"]


@pytest.mark.parametrize("module", PURE)
def test_pure_module_imports_no_io(module: str) -> None:
    code = (
        "import sys\n"
        "before = set(sys.modules)\n"
        f"import {module}\n"
        "new = set(sys.modules) - before\n"
        f"bad = [m for m in {FORBIDDEN!r} if m in new]\n"
        "print(','.join(bad))\n"
    )
    # -I: isolated, -S: no site, so nothing but the module under test is imported
    out = subprocess.run([sys.executable, "-S", "-c", f"import sys; sys.path[:0] = {sys.path!r}\n" + code],
                         capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "", f"{module} imports {out.stdout.strip()}"
