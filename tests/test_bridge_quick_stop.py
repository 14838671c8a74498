"""A quick stop that another master, an input or the drive's heartbeat reaction
starts while the bridge prepares or runs a move is never undone by the bridge.

With quick stop option code 605Ah = 5..8 (the EPOS4's default 6, maxon's EDS) a
drive stays in QUICK STOP ACTIVE at rest, and a controlword carrying "enable
operation" takes it back to OPERATION ENABLED (CiA 402-2 transition 16). Every
move step writes such a controlword, so each is written only while the drive
shows OPERATION ENABLED (``Cia402.write_while_enabled``). Found by review: a
quick stop during ``2S00=1``'s preparation was undone and the axis moved 15 mm.
Here the quick stop arrives at a chosen request of the move, on the real epos
path (tests/bridge_sim.py), as another master's SDO download on the drives' bus.
"""
from __future__ import annotations

import time
from typing import Iterator, List

import pytest

from epos_link.cia402 import State
from epos_link.framing import decode_frames
from epos_link.messages import ReadObject, WriteObject, decode_request
from tcp_bridge.wire import Status
from tests.bridge_sim import SimBridge, run_velocity_move

NODE = 2
QUICK_STOP = 0x000B  # CiA 402-2 6.4.1.2: quick stop command, bits 0..3 = x011 (bit 2 low)


@pytest.fixture
def bridge() -> Iterator[SimBridge]:
    b = SimBridge(drives=(NODE,))
    yield b
    b.close()


def quick_stop_on(bridge: SimBridge, index: int, kind: type = WriteObject) -> List[int]:
    """Quick-stop the drive as another master does, as soon as the bridge's write of
    ``index`` (or, with ``kind`` ReadObject, its read) to it goes out (before the
    drive executes it). Returns a list that gets one entry when it fired."""
    fired: List[int] = []
    plain = bridge.transport.write

    def write(data: bytes) -> int:
        for frame in decode_frames(data):
            try:
                message = decode_request(frame)
            except Exception:
                continue
            if (isinstance(message, kind) and getattr(message, "node", None) == NODE
                    and getattr(message, "index", None) == index and not fired):
                fired.append(1)
                bridge.other_master_write(NODE, 0x6040, 0, QUICK_STOP, 2)
        return plain(data)

    bridge.transport.write = write  # type: ignore[method-assign]
    return fired


def transitions(bridge: SimBridge) -> List[int]:
    return [number for _, number, _ in bridge.drive(NODE).history]


def test_the_maxon_default_keeps_a_quick_stopped_drive_in_quick_stop_active(bridge: SimBridge) -> None:
    assert bridge.other_master_read(NODE, 0x605A, 0) == 6


def test_a_quick_stop_during_a_position_move_s_preparation_is_not_undone(bridge: SimBridge) -> None:
    """The quick stop lands as the target 607Ah goes out; the controlword writes that
    follow (bit 4 low, then the start edge) each read the state first and refuse.
    What remains is the round trip between that read and its write: a quick stop
    landing exactly there is undone, as with any master that writes 6040h by SDO."""
    bridge.ok(f"{NODE}S04=1", f"{NODE}S02=100")
    fired = quick_stop_on(bridge, 0x607A)
    reply = bridge.ask(f"{NODE}S00=1")
    assert fired and reply.status is Status.NAK  # the move did not start: no ACK
    time.sleep(0.3)  # a move of 100 mm would be well under way by now
    drive = bridge.now(NODE)
    assert drive.state is State.QUICK_STOP_ACTIVE and drive.position == 0
    assert 16 not in transitions(bridge)  # never taken back to OPERATION ENABLED
    assert drive.motion_starts == 0


def test_a_quick_stop_during_a_velocity_start_is_not_undone(bridge: SimBridge) -> None:
    bridge.ok(f"{NODE}S04=1", f"{NODE}S07=3", f"{NODE}S05=5")
    fired = quick_stop_on(bridge, 0x60FF)
    reply = bridge.ask(f"{NODE}S00=3")
    assert fired and reply.status is Status.NAK
    time.sleep(0.3)
    drive = bridge.now(NODE)
    assert drive.state is State.QUICK_STOP_ACTIVE and drive.velocity == 0
    assert 16 not in transitions(bridge)


def test_a_running_velocity_move_changed_while_quick_stopped_is_nak(bridge: SimBridge) -> None:
    """Issue 30 finding 6, as it was seen: a velocity move turns, the drive quick-stops
    (another master here; an input or its 6007h reaction alike) while the bridge
    prepares a new speed for it, and S00=3 answered ACK with R86=1 although the drive
    stayed in QUICK STOP ACTIVE: the running-move path wrote 60FFh with no state
    check. The quick stop lands as the bridge reads the controlword, after the
    move's own enabled check: the state read before 60FFh refuses."""
    run_velocity_move(bridge, NODE)
    held = bridge.other_master_read(NODE, 0x60FF, 0, signed=True)
    bridge.ok(f"{NODE}S05=10")
    fired = quick_stop_on(bridge, 0x6040, ReadObject)
    reply = bridge.ask(f"{NODE}S00=3")
    assert fired
    assert reply.status is Status.NAK
    assert bridge.ok(f"{NODE}R86") == "0"  # not started: the drive took no new speed
    bridge.wait_until(lambda: bridge.now(NODE).velocity == 0, why="the quick stop never ended")
    assert bridge.now(NODE).state is State.QUICK_STOP_ACTIVE
    assert bridge.other_master_read(NODE, 0x60FF, 0, signed=True) == held  # nothing written
    assert 16 not in transitions(bridge)


def test_r04_says_power_on_in_quick_stop_active_and_s04_1_is_what_re_enables(bridge: SimBridge) -> None:
    """Spec 3.5, 04: 0 = Power OFF, 1 = Power ON. The power stage stays on in QUICK
    STOP ACTIVE, so R04 is 1 there; a move is still refused until a client's S04=1."""
    bridge.ok(f"{NODE}S04=1")
    bridge.other_master_write(NODE, 0x6040, 0, QUICK_STOP, 2)
    assert bridge.now(NODE).state is State.QUICK_STOP_ACTIVE
    assert bridge.ok(f"{NODE}R04") == "1"
    bridge.ok(f"{NODE}S02=10")
    assert bridge.ask(f"{NODE}S00=1").status is Status.NAK
    assert bridge.now(NODE).state is State.QUICK_STOP_ACTIVE
    bridge.ok(f"{NODE}S04=1")  # the client asks: the enable sequence leaves the quick stop
    assert bridge.now(NODE).state is State.OPERATION_ENABLED
    assert 16 not in transitions(bridge)  # through SWITCH ON DISABLED, not transition 16
