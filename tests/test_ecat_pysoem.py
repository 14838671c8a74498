"""Simulated EPOS4 EtherCAT slaves against a real master: SOEM (pysoem) on a veth pair.

The simulator runs as ``epos-link sim --ethercat`` in its own process: pysoem holds
the GIL inside SOEM calls (config_init waits for frames with it held), so a slave
thread in the master's process could never answer. Skips with the reason when this
machine cannot (not root, no iproute2, no veth, no pysoem).
"""
from __future__ import annotations

import struct
import subprocess
import sys
import time
from typing import Any, Iterator

import pytest

from tests.ecat_veth import unavailable_reason, veth_pair
from tests.helpers import wait_until

REASON = unavailable_reason()
pytestmark = pytest.mark.skipif(REASON is not None, reason=REASON or "")

RX = struct.Struct("<HiiB")     # 6040h, 607Ah, 60FFh, 6060h: the EtherCAT default of 1600h
TX = struct.Struct("<HiiBH")    # 6041h, 6064h, 606Ch, 6061h, 603Fh: 1A00h
CSP = 8


@pytest.fixture
def line() -> Iterator[tuple[Any, Any]]:
    """(pysoem master in PRE-OP after config_init, the simulator process) with 2 slaves."""
    import pysoem

    try:
        pair = veth_pair()
        master_end, slave_end = pair.__enter__()
    except RuntimeError as exc:
        pytest.skip(f"EtherCAT tests need a veth pair: {exc}")
    proc = subprocess.Popen([sys.executable, "-m", "epos_link.cli", "sim", "--ethercat", slave_end,
                             "--slaves", "2"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    master = pysoem.Master()
    try:
        assert proc.stdout is not None and proc.stderr is not None
        line_ = proc.stdout.readline()
        assert "EtherCAT" in line_, (line_, proc.stderr.read() if proc.poll() is not None else "")
        master.open(master_end)
        yield master, proc
    finally:
        master.close()
        proc.terminate()
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        pair.__exit__(None, None, None)


def cycle(master: Any) -> int:
    master.send_processdata()
    return int(master.receive_processdata(20_000))  # us; far above a veth round trip


def inputs(slave: Any) -> tuple[int, int, int, int, int]:
    return TX.unpack(bytes(slave.input))


def test_soem_finds_configures_and_runs_the_simulated_drives(line: tuple[Any, Any]) -> None:
    import pysoem

    master, _proc = line
    assert master.config_init() == 2
    for slave in master.slaves:
        assert (slave.man, slave.id, slave.rev) == (0xFB, 0x69500000, 0x01700000)
        assert slave.name == "EPOS4"
    drive = master.slaves[0]
    assert drive.sdo_read(0x1018, 1) == struct.pack("<I", 0xFB)
    assert drive.sdo_read(0x1008, 0) == b"EPOS4"  # 1008h: a normal (not expedited) upload
    drive.sdo_write(0x605A, 0, struct.pack("<h", 6))  # quick stop, then stay in QUICK STOP ACTIVE
    io_size = master.config_map()
    assert io_size == 2 * (RX.size + TX.size)
    assert master.state_check(pysoem.SAFEOP_STATE, 5_000_000) == pysoem.SAFEOP_STATE

    for slave in master.slaves:
        slave.output = RX.pack(0, 0, 0, CSP)
    master.state = pysoem.OP_STATE
    master.write_state()
    deadline = time.monotonic() + 20
    while master.state_check(pysoem.OP_STATE, 1000) != pysoem.OP_STATE:
        cycle(master)
        assert time.monotonic() < deadline, "no OP"
    assert master.expected_wkc == 2 * 3  # per slave: LRW writes (2) and reads (1)
    assert cycle(master) == master.expected_wkc
    assert inputs(drive)[3] == CSP  # 6061h shows the mode written through 6060h

    # Enable: shutdown, switch on + enable operation (CiA 402-2 6.4.1), through the PDOs.
    start = inputs(drive)[1]
    for controlword, state in ((0x0006, 0x21), (0x000F, 0x27)):
        drive.output = RX.pack(controlword, start, 0, CSP)

        def reached(s: int = state) -> bool:
            cycle(master)
            return inputs(drive)[0] & 0x6F == s
        wait_until(reached, timeout=20, why=f"statusword never showed state 0x{state:02X}")

    # csp: stream set-points 2 ms apart, a ramp of 4000 increments.
    for k in range(1, 401):
        drive.output = RX.pack(0x000F, start + 10 * k, 0, CSP)
        assert cycle(master) == master.expected_wkc
        time.sleep(0.002)
    target = start + 4000

    def followed() -> bool:
        cycle(master)
        return abs(inputs(drive)[1] - target) <= 10
    wait_until(followed, timeout=20, why="6064h never reached the streamed target")
    assert inputs(drive)[0] & 0x6F == 0x27  # still OPERATION ENABLED

    # A move, then the master goes quiet mid-move: the slave's SM2 watchdog (100 ms).
    for k in range(1, 101):
        drive.output = RX.pack(0x000F, target + 20 * k, 0, CSP)
        cycle(master)
        time.sleep(0.002)
    moving = inputs(drive)[1]
    assert moving > target
    time.sleep(1.0)  # no process data: ten watchdog times
    master.read_state()
    assert drive.state == pysoem.SAFEOP_STATE | pysoem.STATE_ERROR
    assert drive.al_status == 0x001B  # sync manager watchdog
    statusword = struct.unpack("<H", drive.sdo_read(0x6041, 0))[0]
    assert statusword & 0x6F == 0x07  # QUICK STOP ACTIVE (605Ah = 6: stays there)
    first = struct.unpack("<i", drive.sdo_read(0x6064, 0))[0]
    time.sleep(0.2)
    assert struct.unpack("<i", drive.sdo_read(0x6064, 0))[0] == first  # at rest
    assert first <= target + 2000  # csp: no further than the last set-point

    other = master.slaves[1]  # the second drive saw the same watchdog (read_state read both)
    assert (other.state, other.al_status) == (pysoem.SAFEOP_STATE | pysoem.STATE_ERROR, 0x001B)
