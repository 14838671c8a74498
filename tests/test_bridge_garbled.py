"""A garbled answer is not silence (issue 24 point 10, must show 6).

A trial served the ``epos`` backend with 5% of the EPOS4's reply bytes
corrupted: 60 of 100 position reads spaced 0.1 s apart answered NAK, because
each CRC error (after the client's one retry) made the bridge declare the
device silent until its next probe (0.25 s later), and the probe's one
attempt was garbled as often. The rule now (:mod:`tcp_bridge.bus.sdo`): a
garbled answer is retried, as the client retries it; only a device that says
nothing, or garbles every attempt, closes the bus.

Over TCP and the bridge against the simulated EPOS4 (``tests/bridge_sim.py``).
The spacing keeps the trial's relation to the probe interval (0.1 s against
0.25 s: two or three reads per probe interval) at a fifth of the time.
"""
from __future__ import annotations

import time
import types
from typing import Iterator, List, Optional

import pytest
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from epos_link.errors import (CrcError, DeviceError, EposTimeoutError, MessageFormatError,
                              TransportError)
from epos_link.simulator.link import LinkOptions
from tcp_bridge.bus.health import Silence
from tcp_bridge.bus.sdo import (GARBLED_RETRIES, NodeSilent, SdoPort, garbled, retry_garbled,
                                silence_of)
from tcp_bridge.errors import DeviceFailure
from tcp_bridge.wire import Status
from tests.bridge_sim import SimBridge
from tests.test_bridge_health import wrapped
from tests.test_bridge_noisy_moves import at_rest

PROBE_INTERVAL = 0.05  # the trial's 0.25 s, scaled by 1/5
SPACING = 0.02  # the trial's 0.1 s, scaled the same
# The link answers at once (sim://); 20 ms is ample for an in-process answer and
# keeps the cost of an answer whose length byte was garbled small.
CLIENT_TIMEOUT = 0.02


@pytest.fixture
def bridge() -> Iterator[SimBridge]:
    b = SimBridge(drives=(2,), timing={"probe_interval": PROBE_INTERVAL},
                  client_timeout=CLIENT_TIMEOUT)
    yield b
    b.close()


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_under_5_percent_reply_corruption_95_of_100_reads_answer_ack(
        bridge: SimBridge, seed: int) -> None:
    b = bridge
    b.ok("2S04=1", "2S05=50", "2S06=1000", "2S02=1.234", "2S00=1")  # a position to read back
    at_rest(b, 2)
    want = b.ok("2R10")  # read on a clean link
    assert float(want) != 0
    b.transport.add_noise(LinkOptions(corrupt=0.05, seed=seed))
    answers: List[str] = []
    for _ in range(100):
        reply = b.ask("2R10")
        if reply.status is not Status.ACK:
            answers.append(reply.status.name)
        elif reply.value != want:
            answers.append(f"ACK {reply.value}")  # never: a damaged answer is never taken
        else:
            answers.append("ok")
        time.sleep(SPACING)
    corrupted = b.transport.faults.corrupted
    assert corrupted > 100  # the link really was noisy
    assert answers.count("ok") >= 95, answers
    assert all(a in ("ok", "NAK") for a in answers), answers


def test_a_link_that_garbles_everything_still_closes_the_bus(bridge: SimBridge) -> None:
    b = bridge
    b.transport.add_noise(LinkOptions(corrupt=1.0, seed=1))
    assert b.ask("2R10").status is Status.NAK  # every try garbled: as good as silent
    health = b.engine.guards["can1"].health
    assert health.silent
    assert b.ask("2R10").status is Status.NAK  # refused at once, no transfer
    b.transport.add_noise(LinkOptions())
    b.wait_until(lambda: not health.silent, why="the bus was never reopened")
    assert b.ask("2R10").status is Status.ACK


# --- the rule, unit by unit ----------------------------------------------------------------


def test_garbled_tells_a_damaged_answer_from_silence() -> None:
    assert garbled(CrcError("bad crc")) and garbled(wrapped(CrcError("bad crc")))
    assert garbled(wrapped(MessageFormatError("short")))
    assert garbled(wrapped(EposTimeoutError("no answer (3 bytes)", heard=True)))
    assert not garbled(wrapped(EposTimeoutError("no answer")))  # silence
    assert not garbled(wrapped(TransportError("port gone")))
    assert not garbled(SdoAbortedError(0x05040000)) and not garbled(DeviceError(0x06020000))
    assert not garbled(SdoCommunicationError("No SDO response received"))  # canopen
    # After its tries, a garbled transfer is the device's silence, as before.
    assert silence_of(wrapped(CrcError("bad crc"))) is Silence.LINK


class ScriptedSdo:
    """node.sdo whose transfers fail with ``errors`` in turn, then answer."""

    def __init__(self, *errors: Exception) -> None:
        self.errors = list(errors)
        self.calls = 0

    def _next(self) -> None:
        self.calls += 1
        if self.errors:
            raise self.errors.pop(0)

    def upload(self, index: int, subindex: int) -> bytes:
        self._next()
        return (0x1234).to_bytes(4, "little")

    def download(self, index: int, subindex: int, data: bytes) -> None:
        self._next()


def port_of(sdo: ScriptedSdo, outcomes: List[Optional[Silence]]) -> SdoPort:
    node = types.SimpleNamespace(sdo=sdo)
    # The port records each transfer's outcome in its node's health (bus.health.NodeHealth).
    health = types.SimpleNamespace(record=lambda silence, why="": outcomes.append(silence))
    return SdoPort(node, health=health)  # type: ignore[arg-type]


def test_a_garbled_answer_is_tried_again_and_the_answer_counts() -> None:
    outcomes: List[Optional[Silence]] = []
    sdo = ScriptedSdo(*[wrapped(CrcError("bad crc"))] * GARBLED_RETRIES)
    port = port_of(sdo, outcomes)
    assert port.read(0x6064) == 0x1234
    assert sdo.calls == GARBLED_RETRIES + 1 and outcomes == [None]  # answered, never silent
    sdo.errors = [wrapped(EposTimeoutError("x", heard=True))]
    port.write(0x607A, 0, 5)
    assert sdo.calls == GARBLED_RETRIES + 3 and outcomes == [None, None]


def test_every_try_garbled_is_silence_and_silence_is_not_tried_again() -> None:
    outcomes: List[Optional[Silence]] = []
    sdo = ScriptedSdo(*[wrapped(CrcError("bad crc"))] * (GARBLED_RETRIES + 1))
    port = port_of(sdo, outcomes)
    with pytest.raises(NodeSilent):
        port.read(0x6064)
    assert sdo.calls == GARBLED_RETRIES + 1 and outcomes == [Silence.LINK]
    sdo = ScriptedSdo(wrapped(EposTimeoutError("no answer")))  # silence: fail fast
    port = port_of(sdo, outcomes)
    with pytest.raises(NodeSilent):
        port.read(0x6064)
    assert sdo.calls == 1 and outcomes[-1] is Silence.LINK
    sdo = ScriptedSdo(SdoAbortedError(0x06020000))  # an abort: an answer, final
    port = port_of(sdo, outcomes)
    with pytest.raises(DeviceFailure):
        port.read(0x6064)
    assert sdo.calls == 1 and outcomes[-1] is None


def test_retry_garbled_tells_each_retry() -> None:
    seen: List[Exception] = []
    sdo = ScriptedSdo(CrcError("a"), CrcError("b"))
    assert retry_garbled(lambda: sdo.upload(0, 0), seen.append) == (0x1234).to_bytes(4, "little")
    assert [str(e) for e in seen] == ["a", "b"]
