"""Tests of tcp_bridge.bus.health (fail-fast buses, issue 12): the state machine on a fake clock,
and tcp_bridge.bus.sdo.silence_of, which tells a silent bus's device from a silent node."""
from __future__ import annotations

import logging
from typing import List, Optional

import can
import pytest
from canopen import SdoAbortedError, SdoCommunicationError
from hypothesis import given, strategies as st

from epos_link.errors import DeviceError, EposTimeoutError, TransportError
from tcp_bridge.bus.failfast import log_change
from tcp_bridge.bus.health import BusHealth, Change, Silence
from tcp_bridge.bus.sdo import silence_of


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def health(**options: float) -> "tuple[BusHealth, Clock]":
    clock = Clock()
    return BusHealth("can1", clock, probe_interval=0.25, **options), clock


# --- the bus's device ------------------------------------------------------------------


def test_one_silent_transfer_is_only_a_suspicion_until_the_probe_confirms_it() -> None:
    h, clock = health()
    h.record(2, Silence.LINK, "no answer")
    assert h.refusal(2) is None  # nothing refused on one lost exchange
    assert h.suspects() == [None]  # the device is probed before the job's reply
    h.probed(None, Silence.LINK, "still no answer")
    assert h.silent and h.suspects() == []
    reason = h.refusal(2)
    assert reason is not None and "bus can1: device silent for 0.0 s" in reason
    assert h.refusal(7) is not None and h.refusal(None) is not None  # every node of the bus
    clock.now += 3
    assert "silent for 3.0 s" in (h.refusal(2) or "")


def test_a_suspicion_the_probe_does_not_confirm_closes_nothing() -> None:
    h, _ = health()
    h.record(2, Silence.LINK, "one lost answer")
    h.probed(None, None)
    assert not h.silent and h.suspects() == [] and h.refusal(2) is None


def test_silent_device_is_probed_every_interval_and_reopens_on_an_answer(
        caplog: pytest.LogCaptureFixture) -> None:
    h, clock = health()
    h.on_change = log_change
    with caplog.at_level(logging.WARNING, logger="tcp_bridge.bus.failfast"):
        h.record(1, Silence.LINK, "timeout")
        h.probed(None, Silence.LINK, "timeout")
        assert h.due() == [] and h.next_due() == pytest.approx(0.25)
        clock.now += 0.25
        assert h.due() == [None]
        h.probed(None, Silence.LINK, "timeout")
        assert h.next_due() == pytest.approx(0.25)  # the device's interval does not grow
        clock.now += 1.5
        h.probed(None, None)
    assert not h.silent and h.refusal(1) is None and h.next_due() is None
    messages = [r.getMessage() for r in caplog.records]
    assert messages[0].startswith("bus can1: device silent (timeout)")
    assert messages[1] == "bus can1: device answers again after 1.8 s silent; its commands are served"
    assert len(messages) == 2  # one line per change of state, none per probe


def test_a_backend_words_its_silent_device_in_the_log(caplog: pytest.LogCaptureFixture) -> None:
    h, clock = health()
    h.on_change = lambda change: log_change(
        change, describe=lambda why: f"the EPOS4 at socket://x:1 does not answer ({why}): check it")
    with caplog.at_level(logging.WARNING, logger="tcp_bridge.bus.failfast"):
        h.probed(None, Silence.LINK, "timeout")
        h.probed(None, None)
    messages = [r.getMessage() for r in caplog.records]
    assert messages[0] == ("bus can1: the EPOS4 at socket://x:1 does not answer (timeout): check "
                           "it; its commands answer NAK at once until a probe gets an answer")
    assert messages[1].startswith("bus can1: device answers again")


def test_each_change_of_state_is_reported_once() -> None:
    h, clock = health()
    changes: List[Change] = []
    h.on_change = changes.append
    h.record(4, Silence.NODE, "abort 0x05040000")
    h.probed(4, Silence.NODE, "abort 0x05040000")
    clock.now += 1.0
    h.probed(4, Silence.NODE)
    clock.now += 1.0
    h.probed(4, None)
    assert changes == [Change("bus can1: node 4", True, "abort 0x05040000"),
                       Change("bus can1: node 4", False, duration=2.0)]


def test_any_answer_reopens_a_silent_device() -> None:
    # A stop is tried even on a silent bus; its answer reopens the bus at once.
    h, _ = health()
    h.record(1, Silence.LINK)
    h.probed(None, Silence.LINK)
    h.record(1, None)
    assert not h.silent


# --- one node --------------------------------------------------------------------------


def test_an_absent_node_behind_a_healthy_gateway_is_not_a_silent_bus() -> None:
    h, _ = health()
    h.record(4, Silence.NODE, "SDO abort 0x05040000")
    assert h.suspects() == [4]
    h.probed(4, Silence.NODE, "SDO abort 0x05040000")
    assert not h.silent and h.node_silent(4)
    assert h.refusal(4) is not None
    assert h.refusal(1) is None and h.refusal(2) is None and h.refusal(None) is None


def test_probes_of_a_silent_node_back_off_to_five_seconds() -> None:
    h, clock = health()
    h.record(4, Silence.NODE)
    h.probed(4, Silence.NODE)
    intervals: List[Optional[float]] = []
    for _ in range(7):
        intervals.append(h.next_due())
        clock.now += h.next_due() or 0.0
        assert h.due() == [4]
        h.probed(4, Silence.NODE)
    assert intervals == pytest.approx([0.25, 0.5, 1.0, 2.0, 4.0, 5.0, 5.0])
    h.probed(4, None)
    assert not h.node_silent(4) and h.next_due() is None


def test_a_node_answering_clears_its_suspicion_and_the_devices() -> None:
    h, _ = health()
    h.record(4, Silence.NODE)
    h.record(4, None)
    assert h.suspects() == []
    h.record(1, Silence.LINK)
    h.record(4, Silence.NODE)  # the gateway spoke for node 4: the device answers
    assert h.suspects() == [4]


def test_behind_a_silent_device_only_the_device_is_probed() -> None:
    h, clock = health()
    h.record(4, Silence.NODE)
    h.probed(4, Silence.NODE)
    h.record(2, Silence.LINK)
    h.probed(None, Silence.LINK)
    clock.now += 10
    assert h.due() == [None]
    h.probed(None, None)
    assert not h.silent and h.due() == [4]  # the node's own silence is still there


def test_a_node_probe_that_finds_the_device_silent_declares_the_bus() -> None:
    h, _ = health()
    h.record(4, Silence.NODE)
    h.probed(4, Silence.LINK)
    assert h.silent and h.due() == [None]


@given(st.lists(st.tuples(st.sampled_from(["record", "probed", "tick"]),
                          st.sampled_from([None, 1, 2, 3]),
                          st.sampled_from([None, Silence.LINK, Silence.NODE])), max_size=60))
def test_refusal_follows_the_declarations_and_waits_stay_bounded(steps: list) -> None:
    h, clock = health()
    for what, target, silence in steps:
        if what == "record":
            h.record(target, silence)
        elif what == "probed":
            h.probed(target, silence)
        else:
            clock.now += 0.3
        # A refusal exists exactly when the device or that node is declared silent.
        for node in (1, 2, 3):
            assert (h.refusal(node) is not None) == (h.silent or h.node_silent(node))
        wait = h.next_due()
        assert wait is None or 0.0 <= wait <= 5.0
        assert (wait is None) == (not h.silent and not any(h.node_silent(n) for n in (1, 2, 3)))


# --- who was silent: tcp_bridge.bus.sdo.silence_of ------------------------------------------


def wrapped(inner: BaseException) -> SdoCommunicationError:
    """As epos_link.canopen_adapter raises it: SdoCommunicationError from the client's error."""
    try:
        try:
            raise inner
        except Exception as exc:
            raise SdoCommunicationError(str(exc)) from exc
    except SdoCommunicationError as outer:
        return outer


def test_silence_of_tells_the_device_from_the_node() -> None:
    # epos/sim backends: the EPOS4 gave no answer at all: the bus's device.
    assert silence_of(wrapped(EposTimeoutError("no answer"))) is Silence.LINK
    assert silence_of(wrapped(TransportError("port gone"))) is Silence.LINK
    assert silence_of(EposTimeoutError("no answer")) is Silence.LINK  # the backend's probe
    # The gateway's "SDO protocol timed out" for a node behind it (CiA 301): the node.
    assert silence_of(SdoAbortedError(0x05040000)) is Silence.NODE
    # canopen backend: no SDO response from the node; the adapter sent fine.
    assert silence_of(SdoCommunicationError("No SDO response received")) is Silence.NODE
    # canopen backend: the adapter itself failed (bus-off, interface down).
    assert silence_of(can.CanOperationError("Network is down")) is Silence.LINK
    assert silence_of(OSError(100, "Network is down")) is Silence.LINK
    # An abort is an answer: nothing was silent.
    assert silence_of(SdoAbortedError(0x06020000)) is None
    assert silence_of(DeviceError(0x06020000)) is None
