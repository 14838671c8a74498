"""Issue 26: internal axes in cyclic synchronous position mode, moved by the bridge's own
profile, and command 90 (LINR / LINA) on one line.

The bridge runs the ``canopen`` backend on the embedded simulator's virtual CAN
bus (``sim`` with ``link = "can"``), in this process; two simulated drives
(nodes 2 and 3, behind gateway node 1, which is no axis) are the internal axes,
``cyclic = "csp"``. A sampler thread reads both drives' positions from the
simulator's drive models (under each drive's lock, synced to now) while they
move. No bound here is a tight wall-clock bound: the checks are about the
shape of the motion, with margins for a loaded 2-core machine.
"""
from __future__ import annotations

import threading
import time
from typing import Any, Dict, Iterator, List, Tuple

import pytest

from epos_link.cia402 import State
from tcp_bridge.engine import Engine, build_engine
from tcp_bridge.errors import InvalidCommand
from tcp_bridge.tables.axes import AxisTable, ConfigError, simulated_increments_per_revolution
from tcp_bridge.wire import Status, decode_reply, parse_request
from tests.drive_samples import DriveSampler, SentSetpoints, largest_change, velocities
from tests.helpers import wait_until

TIMING = {"ack_timeout": 2.0, "state_timeout": 1.0, "reset_timeout": 3.0, "reset_delay": 0.05,
          "poll_interval": 0.002}
FACTOR = 1000  # increments per mm (user unit)
VELOCITY, ACCELERATION, STOP = 20, 40, 80  # mm/s, mm/s^2 (05, 06, 28)
NODES = (2, 3)
Sample = Tuple[float, int, int, State, State]  # time, position of 2, of 3, states


# Margins for a loaded 2-core machine (issue 32): with heartbeat_ms 50 the drives' consumers
# (3 x 50 ms) tripped when the set-point thread, which sends the heartbeat, waited 150 ms
# for the CPU, and the move ended in QUICK STOP ACTIVE; a 0.3 s SDO timeout (the
# backend's default) once ran out on an answer of the simulated drives. The tests of the
# consumer's own reaction give their heartbeat_ms themselves.
HEARTBEAT_MS = 500
SDO_TIMEOUT = 3.0


def table(heartbeat_ms: int = HEARTBEAT_MS, **bus: object) -> AxisTable:
    options: Dict[str, Any] = {"backend": "sim", "link": "can", "gateway_node_id": 1,
                               "heartbeat_ms": heartbeat_ms, "cycle_ms": 10,
                               "sdo_timeout": SDO_TIMEOUT, **bus}
    return AxisTable.from_mapping({
        "bridge": TIMING, "bus": {"can1": options},
        "axis": [{"device": 5, "node_id": n, "internal": True, "cyclic": "csp",
                  "position_factor": FACTOR,
                  "increments_per_revolution": simulated_increments_per_revolution(),
                  "parameters": {"velocity": VELOCITY, "acceleration": ACCELERATION,
                                 "quickstop_accel": STOP}}
                 for n in NODES]})


def ask(engine: Engine, line: str) -> Tuple[Status, Any]:
    reply = decode_reply(engine.execute_sync(parse_request(line.encode())))
    return reply.status, reply.value


class Sampler(DriveSampler[Sample]):
    """Both drives' positions and states, every few ms, from the simulator's models."""

    def __init__(self, engine: Engine) -> None:
        sim = engine.backends[0].simulator
        self.nodes = [sim.drives[n] for n in NODES]
        super().__init__()

    def now(self) -> Sample:
        values = []
        for node in self.nodes:
            with node.lock:
                node.drive.sync()
                values.append((node.drive.now, node.drive.position, node.drive.state))
        return (values[0][0], values[0][1], values[1][1], values[0][2], values[1][2])


def wait_for_consumers(engine: Engine, nodes: Tuple[int, ...]) -> None:
    """Until each drive's heartbeat consumer is active: it becomes so at the first
    heartbeat after it was set up (CiA 301 7.2.8.3.2.2), up to a period after the move
    started, and a bridge killed before that would not be watched yet."""
    drives = engine.backends[0].simulator.drives

    def armed(n: int) -> bool:
        with drives[n].lock:
            return any(drives[n].comm.heartbeats.active.values())

    wait_until(lambda: all(armed(n) for n in nodes), 10, "a heartbeat consumer never became active")


@pytest.fixture
def engine() -> Iterator[Engine]:
    engine = build_engine(table())
    try:
        yield engine
    finally:
        engine.close()


def enable_both(engine: Engine) -> None:
    for n in (1, 2):  # AxAddr 1 and 2: nodes 2 and 3
        assert ask(engine, f"{n}S04=1")[0] is Status.ACK


# -- S90=1: one line ---------------------------------------------------------------------------


def test_linr_moves_both_axes_along_one_line_to_their_targets(engine: Engine) -> None:
    enable_both(engine)
    assert ask(engine, "1S02=40")[0] is Status.ACK  # LINR: each axis by its own 02
    assert ask(engine, "2S02=-16")[0] is Status.ACK
    sent = SentSetpoints(engine.backends[0].cyclic)
    sampler = Sampler(engine)
    start = sampler.now()
    assert ask(engine, "1S90=1")[0] is Status.ACK
    wait_until(lambda: ask(engine, "1R82")[1] == "1" and ask(engine, "2R82")[1] == "1", 30,
               "the line did not end in target")
    seen = sampler.close()
    targets = (start[1] + 40 * FACTOR, start[2] - 16 * FACTOR)
    assert sampler.now()[1:3] == targets  # both exactly on their targets
    deltas = (targets[0] - start[1], targets[1] - start[2])
    moving = [s for s in seen if s[1:3] != start[1:3]]
    assert len(moving) > 50, "too few samples during the move"
    # On one line: the set-points each cycle sent to both drives (tests/drive_samples.py
    # SentSetpoints: the drives' samples also show when one drive's frame was delayed
    # behind the other's on a loaded machine, by up to 4.6% of the line in a test run).
    pairs = [(v[NODES[0]], v[NODES[1]]) for _, v in sent.positions]
    assert len(pairs) > 50, "too few set-points during the move"
    worst = max(abs((a - start[1]) / deltas[0] - (b - start[2]) / deltas[1]) for a, b in pairs)
    assert worst <= 0.02, f"progress fractions differ by {worst:.3f}"
    assert pairs[-1] == targets
    assert ask(engine, "1R86")[1] == "1" and ask(engine, "1R12")[1] == "40"


def test_lina_brings_both_axes_to_zero_together(engine: Engine) -> None:
    enable_both(engine)
    assert ask(engine, "1S02=6")[0] is Status.ACK
    assert ask(engine, "2S02=3")[0] is Status.ACK
    assert ask(engine, "1S90=1")[0] is Status.ACK
    wait_until(lambda: ask(engine, "2R82")[1] == "1", 30, "first line did not end")
    assert ask(engine, "1S90=2")[0] is Status.ACK
    wait_until(lambda: ask(engine, "1R82")[1] == "1" and ask(engine, "2R82")[1] == "1", 30,
               "LINA did not end in target")
    assert ask(engine, "1R12")[1] == "0" and ask(engine, "2R12")[1] == "0"


def test_a_new_02_after_a_cyclic_move_is_taken_by_the_next_line(engine: Engine) -> None:
    """02 of a cyclic axis is the bridge's (plan.axis.BRIDGE_PROFILE): once the drive is in
    CSP, 607Ah is the stream's, and an S02 written there would be refused."""
    enable_both(engine)
    assert ask(engine, "1S02=6")[0] is Status.ACK and ask(engine, "2S02=3")[0] is Status.ACK
    assert ask(engine, "1S90=1")[0] is Status.ACK
    wait_until(lambda: ask(engine, "1R82")[1] == "1" and ask(engine, "2R82")[1] == "1", 30,
               "first line did not end")
    assert ask(engine, "1S02=-2")[0] is Status.ACK and ask(engine, "2S02=-1")[0] is Status.ACK
    assert ask(engine, "1R02")[1] == "-2"
    assert ask(engine, "1S90=1")[0] is Status.ACK
    wait_until(lambda: ask(engine, "1R82")[1] == "1" and ask(engine, "2R82")[1] == "1", 30,
               "second line did not end")
    assert ask(engine, "1R12")[1] == "4" and ask(engine, "2R12")[1] == "2"


# -- S00=8 and S04=0: ramp down ------------------------------------------------------------------


def stopped_mid_move(engine: Engine, stop: str) -> Tuple[List[Sample], Sample, Sample]:
    enable_both(engine)
    assert ask(engine, "1S02=40")[0] is Status.ACK
    assert ask(engine, "2S02=-16")[0] is Status.ACK
    sampler = Sampler(engine)
    start = sampler.now()
    assert ask(engine, "1S90=1")[0] is Status.ACK
    # cruising at 20 mm/s once axis 2 (node 2) is 15 mm on its way
    wait_until(lambda: sampler.now()[1] - start[1] > 15 * FACTOR, 30, "never got going")
    at_stop = sampler.now()
    assert ask(engine, stop)[0] is Status.ACK
    wait_until(lambda: ask(engine, "1R82")[1] == "1", 30, "the stop did not end")
    time.sleep(0.1)
    return sampler.close(), start, at_stop


@pytest.mark.parametrize("stop", ["1S00=8", "1S90=0", "2S00=8"])
def test_a_stop_mid_move_ramps_down_on_the_line_without_a_step(engine: Engine, stop: str) -> None:
    sent = SentSetpoints(engine.backends[0].cyclic)
    seen, start, at_stop = stopped_mid_move(engine, stop)
    rest = seen[-1]
    assert rest[1] - start[1] < 40 * FACTOR  # stopped short of the target ...
    # ... after braking at 28 (80 mm/s^2 from 20 mm/s: 2.5 mm), not at once
    assert rest[1] - at_stop[1] > 1.5 * FACTOR
    # The set-points node 2 was sent, at the times they were computed for (a loaded
    # machine delays some on their way to the drive: tests/drive_samples.py SentSetpoints).
    v = velocities(SentSetpoints.series(sent.positions, NODES[0], at_stop[0] - 0.1))
    # 28 is 80000 inc/s^2; a step from 20000 inc/s in one 30 ms window would be ~670000
    assert largest_change(v) < 3 * STOP * FACTOR, v
    assert SentSetpoints.series(sent.positions, NODES[0])[-1][1] == rest[1]  # the drive followed
    # both stopped together, on the line
    fractions = ((rest[1] - start[1]) / 40, (rest[2] - start[2]) / -16)
    assert abs(fractions[0] - fractions[1]) <= 0.02 * FACTOR
    assert ask(engine, "2R82")[1] == "1"
    assert rest[3] is State.OPERATION_ENABLED and rest[4] is State.OPERATION_ENABLED


def test_a_disable_mid_move_ramps_down_first(engine: Engine) -> None:
    seen, start, at_stop = stopped_mid_move(engine, "1S04=0")
    assert seen[-1][3] is not State.OPERATION_ENABLED  # disabled ...
    assert seen[-1][4] is State.OPERATION_ENABLED  # ... the other axis stopped, still enabled
    assert seen[-1][1] - at_stop[1] > 1.5 * FACTOR  # after its ramp
    sim = engine.backends[0].simulator
    assert not sim.drives[2].drive.unsafe_stops


# -- a dead bridge ------------------------------------------------------------------------------


@pytest.mark.parametrize("how", ["dead", "stalled"])
def test_a_dead_bridge_ends_in_the_drives_quick_stop_not_a_jump(how: str) -> None:
    """The bridge dies (its set-point thread ends), or only the set-point thread stalls
    (blocked in a bus call) while the process lives: on a bus with cyclic axes that
    thread sends the heartbeat too, so either way the drives' consumers react."""
    # The drives trip 3 s after the last heartbeat (heartbeat_ms 1000): a 60 ms budget
    # once tripped a drive before the move got going on a loaded 2-core machine, and
    # 600 ms did too with two CPU hogs running (issue 32).
    engine = build_engine(table(heartbeat_ms=1000))
    release = threading.Event()
    try:
        backend = engine.backends[0]
        for n in NODES:  # the drives' own limits (a CSP drive follows at 60C5h)
            store = backend.simulator.drives[n].store
            store.write(0x60C5, 0, (1500).to_bytes(4, "little"))  # rpm/s: 50000 inc/s^2
            store.write(0x6085, 0, (3000).to_bytes(4, "little"))  # quick stop: 100000 inc/s^2
        enable_both(engine)
        assert ask(engine, "1S02=40")[0] is Status.ACK
        assert ask(engine, "2S02=-16")[0] is Status.ACK
        sampler = Sampler(engine)
        start = sampler.now()
        assert ask(engine, "1S90=1")[0] is Status.ACK
        wait_until(lambda: sampler.now()[1] - start[1] > 15 * FACTOR, 30, "never got going")
        wait_for_consumers(engine, NODES)
        # No set-point, no heartbeat from now on (no clean release).
        if how == "dead":
            backend.cyclic.kill()
        else:
            backend.cyclic.transport.write_targets = lambda targets: release.wait(30)
        killed = sampler.now()
        wait_until(lambda: sampler.now()[3] is not State.OPERATION_ENABLED, 10,
                   "the heartbeat consumer never reacted")
        wait_until(lambda: len(sampler.seen) > 2 and sampler.seen[-1][1] == sampler.seen[-3][1],
                   10, "the drive never came to rest")
        time.sleep(0.1)
        seen = sampler.close()
        states = {s[3] for s in seen if s[0] > killed[0]}
        assert State.QUICK_STOP_ACTIVE in states  # 6007h = 3 (issue 23's default)
        v = velocities([s for s in seen if s[0] >= killed[0] - 0.1], 1)
        # decelerated at the drive's own limits (60C5h, 6085h), never a step
        assert largest_change(v) < 3 * 100_000, v
        assert seen[-1][1] - killed[1] > 0  # it went on a little, braking
        assert not backend.simulator.drives[2].drive.unsafe_stops
    finally:
        release.set()
        engine.close()


# -- configuration ---------------------------------------------------------------------------


def test_a_cyclic_bus_needs_heartbeat_ms() -> None:
    t = AxisTable.from_mapping({
        "bridge": TIMING, "bus": {"can1": {"backend": "sim", "link": "can", "gateway_node_id": 1}},
        "axis": [{"device": 5, "node_id": 2, "internal": True, "cyclic": "csp",
                  "position_factor": FACTOR,
                  "increments_per_revolution": simulated_increments_per_revolution()}]})
    with pytest.raises(ConfigError, match="heartbeat_ms"):
        build_engine(t)


@pytest.mark.parametrize("axis,message", [
    ({"internal": True, "cyclic": "csv"}, "cyclic: str 'csv' is not a value of this key; an "
     "internal axis is moved in CSP by default now: remove cyclic, or write profile"),
    ({"internal": False, "cyclic": "csp"}, "only an internal axis with a drive"),
    ({"internal": False, "profile": "bridge"}, "only an internal axis with a drive"),
    ({"internal": True, "cyclic": 8}, "cyclic: int 8 is not a value of this key"),
    ({"internal": True, "profile": "csp"}, "profile: must be \"bridge\""),
    ({"internal": True, "cyclic": "csp", "profile": "drive"}, "contradict"),
    ({"internal": True, "position_window": -1}, "position_window: must be increments"),
])
def test_the_cyclic_key_is_checked(axis: Dict[str, Any], message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        AxisTable.from_mapping({
            "bus": {"can1": {"backend": "sim"}},
            "axis": [{"device": 5, "node_id": 2, "position_factor": FACTOR,
                      "increments_per_revolution": 2000, **axis}]})


def test_a_cyclic_axis_on_a_bus_without_process_data_is_refused() -> None:
    t = AxisTable.from_mapping({
        "bus": {"can1": {"backend": "sim"}},  # the epos path: SDO only
        "axis": [{"device": 5, "node_id": 1, "internal": True, "cyclic": "csp",
                  "position_factor": FACTOR,
                  "increments_per_revolution": simulated_increments_per_revolution()}]})
    with pytest.raises(ConfigError, match="cannot stream set-points"):
        build_engine(t)


def test_what_a_cyclic_axis_cannot_do_is_refused_before_anything_moves(engine: Engine) -> None:
    enable_both(engine)
    with pytest.raises(InvalidCommand, match="S00=9 is not available"):  # no homing
        ask(engine, "1S00=9")
    with pytest.raises(InvalidCommand, match="no target position"):  # LINR without 02
        ask(engine, "1S90=1")
    assert ask(engine, "1S05=0")[0] is Status.ACK  # no velocity left (26 unset either)
    with pytest.raises(InvalidCommand, match="no velocity"):
        ask(engine, "1S90=2")


def test_the_profile_limits_stay_in_the_bridge(engine: Engine) -> None:
    store = engine.backends[0].simulator.drives[2].store
    before = {i: store.get_int(i) for i in (0x6081, 0x6083, 0x607F, 0x60C5, 0x6085)}
    for line in ("1S05=33", "1S06=44", "1S26=55", "1S27=66", "1S28=77", "1S04=1", "1S85=1"):
        assert ask(engine, line)[0] is Status.ACK
    assert {i: store.get_int(i) for i in before} == before
    assert ask(engine, "1R05")[1] == "33"


def test_a_single_cyclic_axis_moves_on_s00(engine: Engine) -> None:
    enable_both(engine)
    assert ask(engine, "2S02=5")[0] is Status.ACK
    assert ask(engine, "2S00=1")[0] is Status.ACK
    wait_until(lambda: ask(engine, "2R82")[1] == "1", 30, "S00=1 did not end in target")
    assert ask(engine, "2R12")[1] == "5"
    assert ask(engine, "2S00=2")[0] is Status.ACK  # relative: 5 more
    wait_until(lambda: ask(engine, "2R82")[1] == "1", 30, "S00=2 did not end in target")
    assert ask(engine, "2R12")[1] == "10"


def test_a_quick_stop_from_elsewhere_is_not_undone_by_the_set_points(engine: Engine) -> None:
    """Another master (or the drive itself) quick-stops a drive mid-move with 605Ah = 6
    (maxon's EDS default: stay in QUICK STOP ACTIVE). The bridge's set-point frames
    must not carry an "enable operation" that takes it back to OPERATION ENABLED
    (CiA 402-2 transition 16), where CSP would jump to the latest set-point."""
    sim = engine.backends[0].simulator
    for n in NODES:
        with sim.drives[n].lock:
            sim.drives[n].store.write_value(0x605A, 0, 6)
    enable_both(engine)
    assert ask(engine, "1S02=60")[0] is Status.ACK
    assert ask(engine, "2S02=60")[0] is Status.ACK
    assert ask(engine, "1S90=1")[0] is Status.ACK
    drive = sim.drives[2]
    wait_until(lambda: abs(drive.drive.velocity) > 0, 10, "the move never started")
    with drive.lock:
        drive.store.write_value(0x6040, 0, 0x0002)  # quick stop (CiA 402-2 command table)
    wait_until(lambda: drive.drive.state is State.QUICK_STOP_ACTIVE, 10, "no quick stop")
    time.sleep(0.5)  # many set-point cycles
    with drive.lock:
        drive.drive.sync()
        state = drive.drive.state
    assert state is State.QUICK_STOP_ACTIVE, f"the quick stop was undone: {state.name}"
    # The client enables it again: the drive must not jump to the last set-point.
    with drive.lock:
        drive.drive.sync()
        where = drive.drive.position
    status = ask(engine, "1S04=1")[0]
    time.sleep(0.3)
    with drive.lock:
        drive.drive.sync()
        assert abs(drive.drive.position - where) < FACTOR, (status, where, drive.drive.position)
        assert status is Status.ACK and drive.drive.state is State.OPERATION_ENABLED


@pytest.mark.parametrize("keys,cyclic", [
    ({"internal": True}, "csp"),  # PSI spec 3.2: internal = true alone (issue 31)
    ({"internal": True, "cyclic": "csp"}, "csp"),  # the old key keeps working
    ({"internal": True, "profile": "bridge"}, "csp"),
    ({"internal": True, "profile": "drive"}, None),  # the opt-out: the drive's profile modes
    ({"internal": False}, None),
])
def test_an_internal_axis_with_a_drive_is_moved_in_csp_unless_it_opts_out(
        keys: Dict[str, Any], cyclic: Any) -> None:
    t = AxisTable.from_mapping({
        "bus": {"can1": {"backend": "sim"}},
        "axis": [{"device": 5, "node_id": 2, "position_factor": FACTOR,
                  "increments_per_revolution": 2000, **keys}]})
    assert t.axes[1].cyclic == cyclic


def test_position_window_is_read_from_the_table() -> None:
    t = AxisTable.from_mapping({
        "bus": {"can1": {"backend": "sim"}},
        "axis": [{"device": 5, "node_id": 2, "internal": True, "position_window": 25,
                  "position_factor": FACTOR, "increments_per_revolution": 2000}]})
    assert t.axes[1].position_window == 25
