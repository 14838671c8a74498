"""Issue 26: velocity moves (S00=3) of internal cyclic axes, in cyclic synchronous
velocity mode (CSV, 6060h = 9), on the embedded simulator's virtual CAN bus.

Set-up as in tests/test_bridge_csp.py (``sim`` with ``link = "can"``, nodes 2 and
3 cyclic). The drive's own acceleration limit 60C5h is left at its default
(1000000 rpm/s, far above the profile's), so a step in the bridge's set-points
would show as a step in the motion. Velocities come from the drive models'
positions over windows of 30 ms (inc/s); bounds carry wide margins.
"""
from __future__ import annotations

import time
from typing import Iterator, List, Tuple

import pytest

from epos_link.cia402 import State
from tcp_bridge.engine import Engine, build_engine
from tcp_bridge.errors import DeviceFailure
from tcp_bridge.tables.axes import simulated_increments_per_revolution
from tcp_bridge.wire import Status
from tests.drive_samples import DriveSampler, SentSetpoints, largest_change, velocities
from tests.helpers import wait_until
from tests.test_bridge_csp import FACTOR, STOP, VELOCITY, ask, table, wait_for_consumers

Sample = Tuple[float, int, State, int]  # time, position of node 2, its state, its mode


class Sampler(DriveSampler[Sample]):
    def __init__(self, engine: Engine) -> None:
        self.node = engine.backends[0].simulator.drives[2]
        super().__init__()

    def now(self) -> Sample:
        with self.node.lock:
            d = self.node.drive
            d.sync()
            return d.now, d.position, d.state, int(d.mode)


def velocity_now(sampler: Sampler, span: float = 0.05) -> float:
    a = sampler.now()
    time.sleep(span)
    b = sampler.now()
    return (b[1] - a[1]) / (b[0] - a[0])


def largest_acceleration(commanded: List[Tuple[float, int]]) -> float:
    """The largest |dv/dt| of target velocities sent (60FFh, rpm on an EPOS4), in inc/s^2,
    over windows of 30 ms (a rounding to whole rpm is then at most 1.4% of 28)."""
    rpm = simulated_increments_per_revolution() / 60.0  # inc/s per rpm
    return max(abs(a) for _, a in velocities(commanded)) * rpm


@pytest.fixture
def engine() -> Iterator[Engine]:
    engine = build_engine(table())
    try:
        yield engine
    finally:
        engine.close()


def test_s00_3_ramps_to_05_s00_8_ramps_down_and_s00_1_moves_again(engine: Engine) -> None:
    assert ask(engine, "1S04=1")[0] is Status.ACK
    sent = SentSetpoints(engine.backends[0].cyclic)
    sampler = Sampler(engine)
    assert ask(engine, "1S00=3")[0] is Status.ACK
    assert sampler.now()[3] == 9  # CSV
    cruise = VELOCITY * FACTOR
    wait_until(lambda: abs(velocity_now(sampler) - cruise) < 0.03 * cruise, 30,
               "never reached 05")
    assert ask(engine, "1R82")[1] == "0"  # at 05, not at rest: as for a pv move
    stop_at = sampler.now()
    assert ask(engine, "1S00=8")[0] is Status.ACK
    wait_until(lambda: ask(engine, "1R82")[1] == "1", 30, "the ramp down never ended")
    rest = sampler.now()
    time.sleep(0.1)
    seen = sampler.close()
    v = velocities(seen)
    # Ramps at 06 up and 28 down (inc/s^2), never a step: a step of 20000 inc/s
    # would read about 20000 / 0.03 = 670000 inc/s^2 here. Checked on the target
    # velocities sent, at the times they were computed for (tests/drive_samples.py
    # SentSetpoints: a loaded machine delays some on their way to the drive).
    commanded = SentSetpoints.series(sent.velocities, 2)
    assert largest_acceleration(commanded) < 1.05 * STOP * FACTOR, commanded
    assert commanded[-1][1] == 0  # ended at rest, as the drive did (below)
    rising = [x for x in v if x[0] < stop_at[0] and 0.2 * cruise < x[1] < 0.8 * cruise]
    falling = [x for x in v if x[0] > stop_at[0] and 0.2 * cruise < x[1] < 0.8 * cruise]
    assert rising and falling  # passed through the middle both ways: ramps, not steps
    # the ramp down takes about cruise / 28 = 0.25 s: at least most of it
    assert rest[0] - stop_at[0] > 0.6 * cruise / (STOP * FACTOR)
    probe = Sampler(engine)  # closed: a sampler left running syncs the drive every 4 ms
    try:  # for the rest of the worker's life (seen in a py-spy dump of a suite run)
        assert abs(velocity_now(probe)) == 0
    finally:
        probe.close()
    # a position move works again: back to CSP on the actual position
    here = float(ask(engine, "1R12")[1])
    assert ask(engine, f"1S02={here + 5:g}")[0] is Status.ACK
    assert ask(engine, "1S00=1")[0] is Status.ACK
    wait_until(lambda: ask(engine, "1R82")[1] == "1", 30, "S00=1 did not end in target")
    assert float(ask(engine, "1R12")[1]) == pytest.approx(here + 5, abs=0.01)
    assert engine.backends[0].simulator.drives[2].drive.mode == 8
    assert not engine.backends[0].simulator.drives[2].drive.unsafe_stops


def test_a_negative_05_runs_backwards_and_s04_0_ramps_down_first(engine: Engine) -> None:
    assert ask(engine, "1S04=1")[0] is Status.ACK
    assert ask(engine, f"1S05={-VELOCITY}")[0] is Status.ACK
    sent = SentSetpoints(engine.backends[0].cyclic)
    sampler = Sampler(engine)
    assert ask(engine, "1S00=3")[0] is Status.ACK
    wait_until(lambda: velocity_now(sampler) < -0.9 * VELOCITY * FACTOR, 30, "never got going")
    assert ask(engine, "1S04=0")[0] is Status.ACK  # answered once at rest
    assert sampler.now()[2] is not State.OPERATION_ENABLED
    sampler.close()
    commanded = SentSetpoints.series(sent.velocities, 2)  # as sent (SentSetpoints)
    assert largest_acceleration(commanded) < 1.05 * STOP * FACTOR, commanded
    assert not engine.backends[0].simulator.drives[2].drive.unsafe_stops


def test_a_new_s00_3_during_a_velocity_move_is_refused(engine: Engine) -> None:
    assert ask(engine, "1S04=1")[0] is Status.ACK
    assert ask(engine, "1S00=3")[0] is Status.ACK
    with pytest.raises(DeviceFailure, match="still on a cyclic move"):  # stop it first
        ask(engine, "1S00=3")
    assert ask(engine, "1S00=8")[0] is Status.ACK


def test_a_dead_set_point_thread_ends_in_the_drives_quick_stop_not_a_jump() -> None:
    # The drives trip 3 s after the last heartbeat (heartbeat_ms 1000): a 60 ms budget
    # once tripped a drive before the move got going on a loaded 2-core machine, and
    # 600 ms did too with two CPU hogs running (issue 32).
    engine = build_engine(table(heartbeat_ms=1000))
    try:
        backend = engine.backends[0]
        store = backend.simulator.drives[2].store
        store.write(0x6085, 0, (3000).to_bytes(4, "little"))  # quick stop: 100000 inc/s^2
        assert ask(engine, "1S04=1")[0] is Status.ACK
        sampler = Sampler(engine)
        assert ask(engine, "1S00=3")[0] is Status.ACK
        wait_until(lambda: velocity_now(sampler) > 0.9 * VELOCITY * FACTOR, 30, "never got going")
        wait_for_consumers(engine, (2,))
        backend.cyclic.kill()  # no set-point, no heartbeat from now on
        killed = sampler.now()
        wait_until(lambda: sampler.now()[2] is not State.OPERATION_ENABLED, 10,
                   "the heartbeat consumer never reacted")
        wait_until(lambda: len(sampler.seen) > 2 and sampler.seen[-1][1] == sampler.seen[-3][1],
                   10, "the drive never came to rest")
        seen = sampler.close()
        states = {s[2] for s in seen if s[0] > killed[0]}
        assert State.QUICK_STOP_ACTIVE in states  # 6007h = 3 (issue 23's default)
        v = velocities([s for s in seen if s[0] >= killed[0] - 0.1])
        assert largest_change(v) < 3 * 100_000, v  # braked at 6085h, never a step
        assert seen[-1][1] > killed[1]  # it went on a little, braking
        assert not backend.simulator.drives[2].drive.unsafe_stops
    finally:
        engine.close()
