"""Issue 26 on EtherCAT: two simulated slaves as two internal axes in CSP, their set-points
made on the bridge's process-data cycle (:mod:`tcp_bridge.backends.ethercat_csp`).

A veth pair; on one end the simulated EPOS4 slaves (:class:`EthercatServer`) run in
*this* process, so the test reads the drive models directly (positions, CiA 402
states, the slaves' AL state and status code) without going through the bridge;
on the other end the bridge runs as ``tcp-bridge serve --config`` in a subprocess
(pysoem holds the GIL during its exchanges, and the subprocess is what the
dead-bridge test SIGKILLs). Needs root, iproute2 and pysoem; each missing piece
skips the module with a line saying which.

Sampling margin: the sampler reads the two drives one after the other, each under
its own lock, a few microseconds apart, and the two slaves take each frame's
set-points one after the other too (the simulator handles a frame slave by slave);
at 20 mm/s that is far below the 2 % asked (0.8 mm of the 40 mm line), so the
check is the brief's 2 % without an extra margin. No bound here is a tight
wall-clock bound: the checks are about the shape of the motion.
"""
from __future__ import annotations

import json
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Iterator, List, Tuple

import pytest

from epos_link.cia402 import State
from tcp_bridge.tables.axes import simulated_increments_per_revolution
from tcp_bridge.wire import Status
from tests.ecat_veth import bus_open, unavailable_reason, veth_pair
from tests.drive_samples import DriveSampler, largest_change, velocities
from tests.helpers import psi_ask, wait_until

WHY_NOT = unavailable_reason()
pytestmark = pytest.mark.skipif(bool(WHY_NOT), reason=WHY_NOT or "runs")

ROOT = Path(__file__).resolve().parent.parent
FACTOR = 1000  # increments per mm
VELOCITY, ACCELERATION, STOP = 20, 40, 80  # mm/s, mm/s^2 (05, 06, 28)
Sample = Tuple[float, int, int, State, State]  # time, position of slave 1, of 2, states


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Tuple[object, str]]:
    from epos_link.simulator.ethercat.server import EthercatServer

    try:
        pair = veth_pair()
        master, slave = pair.__enter__()
    except RuntimeError as exc:
        pytest.skip(str(exc))
    events = tmp_path_factory.mktemp("ecat") / "events.jsonl"
    try:
        with EthercatServer(slave, slaves=2, events=str(events)) as sim:
            sim.events_path = events  # type: ignore[attr-defined]
            yield sim, master
    finally:
        pair.__exit__(None, None, None)


# The slaves' SM watchdog in these tables: 1 s, as the motion-rule tests have
# (test_bridge_ethercat_safety.py). With 100 ms a loaded machine (two CPU hogs beside
# the suite) started a cycle 96 ms late, the watchdog tripped, both drives quick-stopped
# and 1S90=1 was NAK ("left the move as it started"): the bridge was right, the test's
# watchdog too tight. What the watchdog does is tested where it is the subject
# (test_bridge_ethercat_recovery.py, test_bridge_ethercat_freeze.py, test_ecat_csp.py).
WATCHDOG_MS = 1000


def write_table(tmp: Path, interface: str, watchdog_ms: int = WATCHDOG_MS) -> Path:
    axes = "".join(
        f"[[axis]]\naddr = {n}\ndevice = 5\nbus_offset = 1000000\nnode_id = {n}\n"
        f"internal = true\ncyclic = \"csp\"\nposition_factor = {FACTOR}\n"
        f"increments_per_revolution = {simulated_increments_per_revolution()}\n"
        f"[axis.parameters]\nvelocity = {VELOCITY}\nacceleration = {ACCELERATION}\n"
        f"quickstop_accel = {STOP}\n\n" for n in (1, 2))
    table = tmp / "axes.toml"
    table.write_text(
        "[bridge]\nack_timeout = 2.0\nstate_timeout = 1.0\nreset_timeout = 3.0\n\n"
        f"[bus.ethercat]\nbackend = \"ethercat\"\ninterface = \"{interface}\"\ncycle_ms = 4\n"
        # 5 s for a CoE transfer, as the safety and recovery tests have: with two CPU
        # hogs the set-up's reads had no answer within the default 0.3 s ("slave 2: PDO
        # mapping unreadable", "slave 1: watchdog not set"), and 2S04=1 was NAK.
        f"watchdog_ms = {watchdog_ms}\nsdo_timeout = 5.0\n\n{axes}")
    return table


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture
def bridge(server: Tuple[object, str], tmp_path: Path) -> Iterator[Tuple[socket.socket,
                                                                          "subprocess.Popen[str]"]]:
    table = write_table(tmp_path, server[1])
    log = tmp_path / "bridge.log"
    port = free_port()
    with log.open("w") as out:
        proc = subprocess.Popen([sys.executable, "-m", "tcp_bridge.cli", "serve", "--config",
                                 str(table), "--port", str(port), "--maintenance-port", "-1", "-v"],
                                cwd=ROOT, stdout=out, stderr=subprocess.STDOUT, text=True)
    try:
        wait_until(lambda: "listening on" in log.read_text() or proc.poll() is not None, 60,
                   "the bridge never listened")
        assert proc.poll() is None, log.read_text()
        wait_until(lambda: bus_open(log.read_text()), 60, "the EtherCAT bus never opened")
        with socket.create_connection(("127.0.0.1", port), timeout=30) as sock:
            yield sock, proc
    finally:
        if proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(10)


def ask(sock: socket.socket, line: str) -> Tuple[Status, str]:
    reply = psi_ask(sock, line)
    return reply.status, reply.value or ""


def ok(sock: socket.socket, *lines: str) -> None:
    for line in lines:
        assert ask(sock, line)[0] is Status.ACK, line


class Sampler(DriveSampler[Sample]):
    """Both drives' positions and states, every few ms, from the simulated slaves."""

    def __init__(self, sim: object) -> None:
        self.drives = list(sim.drives)  # type: ignore[attr-defined]
        super().__init__()

    def now(self) -> Sample:
        values = []
        for d in self.drives:
            with d.lock:
                d.drive.sync()
                values.append((d.drive.now, d.drive.position, d.drive.state))
        return (values[0][0], values[0][1], values[1][1], values[0][2], values[1][2])


def sent_setpoints(sim: object, slave: int, since: float) -> List[Tuple[float, int]]:
    """``(arrival, 607Ah)`` of every frame that changed ``slave``'s set-point since the
    wall time ``since``: the stream as the bridge sent it. The drive model's positions
    lag it by however long this loaded process took to handle each frame, so velocities
    from them show steps that no set-point had (issue 32: the stop test failed once in
    two full runs with two CPU hogs, a 274,000 inc/s^2 'step' in a 20 mm/s ramp)."""
    path: Path = sim.events_path  # type: ignore[attr-defined]
    out = []
    for line in path.read_text().splitlines():
        event = json.loads(line)
        if (event.get("event") == "outputs" and event.get("slave") == slave
                and "sp" in event and "rx" in event and event["rx"] >= since):
            out.append((float(event["rx"]), int(event["sp"])))
    return out


def enable_and_aim(sock: socket.socket) -> None:
    ok(sock, "1S04=1", "2S04=1", "1S02=40", "2S02=-16")  # LINR: each axis by its own 02


def setpoint_frames(sim: object, since: float, first: Tuple[int, int]) -> List[Tuple[int, int]]:
    """Both slaves' set-points after each frame that changed either (the other's is its
    last), from ``first``: what the bridge sent, frame by frame."""
    changes = sorted([(t, 0, sp) for t, sp in sent_setpoints(sim, 1, since)]
                     + [(t, 1, sp) for t, sp in sent_setpoints(sim, 2, since)])
    now, out = list(first), []
    for i, (t, slave, sp) in enumerate(changes):
        now[slave] = sp
        if i + 1 == len(changes) or changes[i + 1][0] != t:  # the frame's last change
            out.append((now[0], now[1]))
    return out


def test_linr_moves_both_slaves_along_one_line(server: Tuple[object, str], bridge) -> None:
    sock, _ = bridge
    enable_and_aim(sock)
    sampler = Sampler(server[0])
    start = sampler.now()
    line_sent = time.time()
    ok(sock, "1S90=1")
    wait_until(lambda: ask(sock, "1R82")[1] == "1" and ask(sock, "2R82")[1] == "1", 60,
               "the line did not end in target")
    seen = sampler.close()
    targets = (start[1] + 40 * FACTOR, start[2] - 16 * FACTOR)
    assert sampler.now()[1:3] == targets  # both exactly on their targets
    moving = [s for s in seen if s[1:3] != start[1:3]]
    assert len(moving) > 50, "too few samples during the move"
    # One line: in every frame, the two set-points the bridge sent are at the same
    # fraction of their travel (here within 4e-5). From the set-points, as the stop test
    # takes them: the drive models, read one after the other, lag the frames by however
    # long this loaded process took to handle each; read so, the fractions differed by
    # 0.031 once on six workers while every frame held one line.
    frames = setpoint_frames(server[0], line_sent - 0.1, (start[1], start[2]))
    assert len(frames) > 50, "too few frames during the move"
    worst = max(abs((a - start[1]) / (40 * FACTOR) - (b - start[2]) / (-16 * FACTOR))
                for a, b in frames)
    assert worst <= 0.02, f"progress fractions differ by {worst:.3f}"
    # the controlword stayed the enable's: both still OPERATION ENABLED after the line
    assert seen[-1][3] is State.OPERATION_ENABLED and seen[-1][4] is State.OPERATION_ENABLED


def test_s00_8_mid_move_ramps_down_without_a_step(server: Tuple[object, str], bridge) -> None:
    sock, _ = bridge
    enable_and_aim(sock)
    sampler = Sampler(server[0])
    start = sampler.now()
    ok(sock, "1S90=1")
    wait_until(lambda: sampler.now()[1] - start[1] > 15 * FACTOR, 60, "never got going")
    at_stop = sampler.now()
    stop_sent = time.time()
    ok(sock, "1S00=8")
    wait_until(lambda: ask(sock, "1R82")[1] == "1", 60, "the stop did not end")
    time.sleep(0.1)
    seen = sampler.close()
    rest = seen[-1]
    assert rest[1] - start[1] < 40 * FACTOR  # short of the target ...
    assert rest[1] - at_stop[1] > 1.5 * FACTOR  # ... after braking at 28 (2.5 mm), not at once
    sent = sent_setpoints(server[0], 1, stop_sent - 0.1)
    assert len(sent) > 20, sent  # the ramp down is 0.25 s of 4 ms cycles
    v = velocities(sent, 1)
    assert largest_change(v) < 3 * STOP * FACTOR, v  # a step would be ~670000 inc/s^2
    fractions = ((rest[1] - start[1]) / 40, (rest[2] - start[2]) / -16)
    assert abs(fractions[0] - fractions[1]) <= 0.02 * FACTOR  # stopped together, on the line
    assert rest[3] is State.OPERATION_ENABLED and rest[4] is State.OPERATION_ENABLED


def test_s00_3_then_s00_8_is_a_velocity_move_in_csv(server: Tuple[object, str], bridge) -> None:
    """S00=3 on slave 1: mode 9, 60FFh ramped to 05 in the outputs; S00=8 ramps it down
    at 28 (20 mm/s at 80 mm/s^2: 2.5 mm), never a step; the drive stays enabled."""
    sock, _ = bridge
    ok(sock, "1S04=1")
    sampler = Sampler(server[0])
    cruise = VELOCITY * FACTOR

    def speed() -> float:
        a = sampler.now()
        time.sleep(0.05)
        b = sampler.now()
        return (b[1] - a[1]) / (b[0] - a[0])
    ok(sock, "1S00=3")
    wait_until(lambda: abs(speed() - cruise) < 0.03 * cruise, 60, "never reached 05")
    drive = server[0].drives[0]  # type: ignore[attr-defined]
    with drive.lock:
        assert int(drive.drive.mode) == 9
    assert ask(sock, "1R82")[1] == "0"  # running at 05: not at rest
    at_stop = sampler.now()
    ok(sock, "1S00=8")
    wait_until(lambda: ask(sock, "1R82")[1] == "1", 60, "the ramp down did not end")
    time.sleep(0.1)
    seen = sampler.close()
    rest = seen[-1]
    assert rest[1] - at_stop[1] > 1.5 * FACTOR  # braked at 28, not at once
    v = velocities(seen, 1)
    assert largest_change(v) < 3 * STOP * FACTOR, v  # a step would be ~670000 inc/s^2
    assert rest[3] is State.OPERATION_ENABLED


def test_a_killed_bridge_ends_in_the_sm_watchdog_reaction_not_a_jump(
        server: Tuple[object, str], bridge) -> None:
    sim = server[0]
    sock, proc = bridge
    for d in sim.drives:  # type: ignore[attr-defined]
        with d.lock:  # the drives' own limits (a CSP drive follows at 60C5h, stops at 6085h)
            d.store.write(0x60C5, 0, (1500).to_bytes(4, "little"))  # 50000 inc/s^2
            d.store.write(0x6085, 0, (3000).to_bytes(4, "little"))  # 100000 inc/s^2
    reactions = [d.watchdog_reactions for d in sim.drives]  # type: ignore[attr-defined]
    enable_and_aim(sock)
    sampler = Sampler(sim)
    start = sampler.now()
    ok(sock, "1S90=1")
    wait_until(lambda: sampler.now()[1] - start[1] > 15 * FACTOR, 60, "never got going")
    proc.send_signal(signal.SIGKILL)  # no clean shutdown: the process data just stop
    proc.wait(30)
    killed = sampler.now()
    wait_until(lambda: all(d.watchdog_reactions > r for d, r in
                           zip(sim.drives, reactions)), 10,  # type: ignore[attr-defined]
               "the SM watchdog never tripped")
    wait_until(lambda: len(sampler.seen) > 2 and sampler.seen[-1][1:3] == sampler.seen[-3][1:3],
               10, "the drives never came to rest")
    time.sleep(0.1)
    seen = sampler.close()
    from epos_link.simulator.ethercat.esc import AL_STATUS, AL_STATUS_CODE
    for d in sim.drives:  # type: ignore[attr-defined]
        with sim.lock:  # type: ignore[attr-defined]
            al, code = d.slave.esc.u16(AL_STATUS), d.slave.esc.u16(AL_STATUS_CODE)
        assert al & 0x0F == 0x04 and code == 0x001B, (hex(al), hex(code))  # SAFE-OP, SM watchdog
    states = {s[3] for s in seen if s[0] > killed[0]} | {s[4] for s in seen if s[0] > killed[0]}
    assert State.QUICK_STOP_ACTIVE in states  # 6007h = 3, maxon's default
    for which in (1, 2):
        v = velocities([s for s in seen if s[0] >= killed[0] - 0.1], which)
        assert largest_change(v) < 3 * 100_000, v  # the drive's own ramps, never a step
    assert seen[-1][1] - killed[1] > 0  # it went on a little, braking
    assert seen[-1][1] - start[1] < 40 * FACTOR  # and did not run to the target
