"""The status page says why (issue 34 item 4): each row's condition for its state cell,
said once; "target reached" only where it means something; ``last error`` cleared when
the command that failed answers again. Pure rows, and the sampler over a scripted engine.
tests/test_bridge_http_browser.py checks the page itself in chromium."""
from __future__ import annotations

import asyncio
from types import SimpleNamespace
from typing import Dict, Optional, Set

import pytest

from tcp_bridge.bus.failfast import BusGuard
from tcp_bridge.bus.health import BusHealth, Silence
from tcp_bridge.errors import DeviceFailure, SilentLink
from tcp_bridge.status.rows import condition, failure_kind, row
from tcp_bridge.status.sampler import Sampler
from tcp_bridge.tables.axes import AxisConfig
from tcp_bridge.wire import ReadRequest, format_read_reply


def refusal(target: Optional[int], why: str) -> SilentLink:
    """The refusal the bridge's fail-fast really gives, for the bus's device or a node."""
    health = BusHealth("can2", clock=lambda: 10.0)
    health.record(target, Silence.LINK if target is None else Silence.NODE, why)
    health.probed(target, Silence.LINK if target is None else Silence.NODE, why)
    found = BusGuard(health, {}).refusal(target if target is not None else 5)
    assert found is not None
    return found


def test_a_refusal_names_its_bus_once() -> None:
    """`bus can1: bus can1: ...` was the page's (and the NAK log's) reason."""
    text = str(refusal(None, "timeout"))
    assert text.startswith("bus can2: device silent for ") and text.count("bus can2") == 1


@pytest.mark.parametrize("exc, kind, reason", [
    (refusal(None, "cannot open /dev/ttyACM0: No such file or directory"), "no bus",
     "bus can2: cannot open /dev/ttyACM0: No such file or directory"),
    (refusal(None, "EPOS4 did not answer within 0.5 s"), "bus silent",
     "bus can2: its device does not answer (EPOS4 did not answer within 0.5 s)"),
    (refusal(5, "No SDO response received"), "silent",
     "node 5 on bus can2 does not answer (No SDO response received)"),
    (DeviceFailure("SDO abort 0x05040000: SDO protocol timed out", code=0x05040000), "silent",
     "SDO abort 0x05040000: SDO protocol timed out"),
    (DeviceFailure("SDO abort 0x06020000: Object does not exist", code=0x06020000), "error",
     "SDO abort 0x06020000: Object does not exist"),
])
def test_each_failure_has_its_kind_and_reason(exc: BaseException, kind: str, reason: str) -> None:
    assert failure_kind(exc) == (kind, reason)


def test_the_reason_is_said_once_for_every_read_it_failed() -> None:
    failures: Dict[int, BaseException] = {
        cmd: SilentLink(f"bus can2: node 5 silent for {10 + cmd / 100:.1f} s (No SDO response "
                        "received); answered at once, a probe reopens it")
        for cmd in (10, 12, 14, 82)}
    assert condition(None, failures, None) == {
        "kind": "silent", "text": "silent",
        "reason": "node 5 on bus can2 does not answer (No SDO response received)"}


def test_fault_says_why_from_the_error_bits_and_worse_failures_come_first() -> None:
    assert condition("fault", {}, ["following error"]) == {
        "kind": "fault", "text": "fault", "reason": "following error"}
    mixed: Dict[int, BaseException] = {
        11: DeviceFailure("SDO abort 0x06020000: Object does not exist", code=0x06020000),
        12: refusal(None, "timeout")}
    found = condition("switch on disabled", mixed, None)
    assert found["kind"] == "bus silent" and found["text"] == "switch on disabled; bus silent"
    assert found["reason"] == ("bus can2: its device does not answer (timeout); "
                               "SDO abort 0x06020000: Object does not exist")
    assert condition("switched on", {}, []) == {"kind": "ok", "text": "switched on", "reason": ""}


CONFIG = AxisConfig(addr=2, node_id=2)


@pytest.mark.parametrize("statusword, reached, shown", [
    ("64", "0", None),    # switch on disabled, at rest: no target, not "no"
    ("1079", "1", True),  # 0x0437 operation enabled, target reached
    ("55", "0", False),   # 0x0037 operation enabled, moving
    ("8", "0", None),     # fault
])
def test_target_reached_only_in_operation_enabled(statusword: str, reached: str,
                                                  shown: Optional[bool]) -> None:
    r = row(CONFIG, {10: statusword, 82: reached}, t=0.0, errors={}, last_error=None)
    assert r["target_reached"] is shown


class ScriptedEngine:
    """An engine whose reads of axis 2 fail for the commands in ``failing``."""

    def __init__(self) -> None:
        self.axes = {2: SimpleNamespace(config=CONFIG, port=object())}
        self.failing: Set[int] = set()

    async def execute(self, request: ReadRequest) -> bytes:
        if request.cmd in self.failing:
            raise DeviceFailure("SDO abort 0x05040000: SDO protocol timed out", code=0x05040000)
        value = {10: 64, 12: 1.5, 14: 0.0, 82: 1, 86: 0, 15: 1, 11: 0}[request.cmd]
        return format_read_reply(request.axis, request.cmd, value)


def test_last_error_is_cleared_when_the_command_answers_again() -> None:
    engine = ScriptedEngine()
    clock = iter(float(t) for t in range(1000))
    sampler = Sampler(engine, clock=lambda: next(clock))

    async def sample() -> dict:
        return (await sampler.sample())["axes"][0]

    async def scenario() -> None:
        assert (await sample())["last_error"] is None
        engine.failing = {10, 12}
        failed = await sample()
        assert failed["condition"]["kind"] == "silent" and failed["state"] is None
        assert failed["last_error"]["cmd"] == 12
        assert failed["last_error"]["error"] == "SDO abort 0x05040000: SDO protocol timed out"
        engine.failing = set()
        recovered = await sample()
        assert recovered["last_error"] is None  # not a stale text after recovery
        assert recovered["condition"] == {"kind": "ok", "text": "switch on disabled",
                                          "reason": ""}

    asyncio.run(scenario())
