"""The NMT rule of the gateway adapter as data, and ``wait_for_bootup`` as a
poll on a scripted link and clock (issue 17; rules in epos_link/canopen_gateway.py)."""
from __future__ import annotations

import pytest
from canopen.nmt import NmtError

from epos_link.canopen_gateway import (OPERATIONAL, PRE_OPERATIONAL, STOPPED, UNKNOWN,
                                       GatewayNmt, NmtView, nmt_view)
from epos_link.codes import NmtCommand
from epos_link.errors import DeviceError, EposTimeoutError, TransportError

START, STOP, PREOP = NmtCommand.START_REMOTE_NODE, NmtCommand.STOP_REMOTE_NODE, NmtCommand.ENTER_PRE_OPERATIONAL
RESET, RESET_COMM = NmtCommand.RESET_NODE, NmtCommand.RESET_COMMUNICATION


# --- the rule, as data ------------------------------------------------------------------


def test_view_unknown_until_answered_then_pre_operational() -> None:
    view = NmtView()
    assert view.state(2) == UNKNOWN
    view.answered(2)
    assert view.state(2) == PRE_OPERATIONAL
    assert view.state(3) == UNKNOWN  # per node


@pytest.mark.parametrize("command,state", [(START, OPERATIONAL), (STOP, STOPPED),
                                           (PREOP, PRE_OPERATIONAL)])
def test_view_a_command_sets_its_state_and_answers_do_not_override_it(command: int, state: int) -> None:
    view = NmtView()
    view.sent(2, command)
    assert view.state(2) == state
    view.answered(2)
    assert view.state(2) == state


@pytest.mark.parametrize("reset", [RESET, RESET_COMM])
def test_view_after_a_reset_unknown_until_the_node_answers_again(reset: int) -> None:
    view = NmtView()
    view.sent(2, START)
    view.answered(2)
    view.sent(2, reset)
    assert view.state(2) == UNKNOWN and view.resetting(2)
    view.answered(2)
    assert view.state(2) == PRE_OPERATIONAL and not view.resetting(2)  # START no longer holds


def test_view_broadcasts_reach_known_nodes_and_nodes_seen_later() -> None:
    view = NmtView()
    view.answered(2)
    view.sent(0, START)
    assert view.state(2) == OPERATIONAL
    assert view.state(5) == OPERATIONAL  # never heard of, but told to start
    view.answered(5)
    assert view.state(5) == OPERATIONAL
    view.sent(0, RESET)
    assert view.resetting(2) and view.resetting(7)
    view.answered(7)
    assert view.state(7) == PRE_OPERATIONAL and view.state(2) == UNKNOWN


def test_view_node_0_is_what_broadcasts_said() -> None:
    view = NmtView()
    assert view.state(0) == UNKNOWN
    view.sent(0, STOP)
    view.answered(0)  # nobody answers for "all nodes"
    assert view.state(0) == STOPPED
    view.sent(2, START)
    assert view.state(0) == STOPPED and view.state(2) == OPERATIONAL


def test_view_unknown_commands_change_nothing() -> None:
    view = NmtView()
    view.answered(2)
    view.sent(2, 0x55)
    assert view.state(2) == PRE_OPERATIONAL


# --- wait_for_bootup as a poll, on a scripted link and clock ----------------------------


class ScriptedLink:
    """Stands in for EposClient.read_object: fails as scripted, each failure
    taking ``cost`` seconds of the fake clock, then answers."""

    def __init__(self, failures: list[BaseException], cost: float) -> None:
        self.failures = failures
        self.cost = cost
        self.now = 0.0
        self.requests: list[tuple[int, int, int]] = []
        self.timeout = 0.5

    def read_object(self, node: int, index: int, subindex: int, **_: object) -> bytes:
        self.requests.append((node, index, subindex))
        self.now += self.cost
        if self.failures:
            raise self.failures.pop(0)
        return (0x00020192).to_bytes(4, "little")

    def sleep(self, seconds: float) -> None:
        assert seconds > 0
        self.now += seconds


def _nmt_after_reset(link: ScriptedLink, node_id: int = 2) -> GatewayNmt:
    nmt = GatewayNmt(node_id, link)  # type: ignore[arg-type]
    nmt.clock = lambda: link.now  # type: ignore[method-assign, assignment]
    nmt.sleep = link.sleep  # type: ignore[method-assign, assignment]
    nmt_view(link).sent(node_id, RESET)  # type: ignore[arg-type]
    return nmt


def test_wait_for_bootup_polls_until_the_node_answers() -> None:
    # Three ways a booting node fails to answer: the gateway's SDO timeout,
    # a link timeout, a link that drops (USB re-enumerating after a reset).
    link = ScriptedLink([DeviceError(0x05040000), EposTimeoutError("silent"),
                         TransportError("gone")], cost=0.3)
    nmt = _nmt_after_reset(link)
    assert nmt.state == "INITIALISING"
    nmt.wait_for_bootup(5)
    assert link.requests == [(2, 0x1000, 0)] * 4
    assert nmt.state == "PRE-OPERATIONAL"


def test_wait_for_bootup_times_out_with_canopens_error() -> None:
    link = ScriptedLink([DeviceError(0x05040000)] * 100, cost=0.3)
    nmt = _nmt_after_reset(link)
    with pytest.raises(NmtError, match="Timeout waiting for boot-up message"):
        nmt.wait_for_bootup(1.0)
    assert len(link.requests) == 4  # 0.3, 0.6, 0.9, 1.2 s: past the deadline after one request
    assert nmt.state == "INITIALISING"


def test_wait_for_bootup_does_not_hammer_a_link_that_fails_at_once() -> None:
    link = ScriptedLink([DeviceError(0x0F00FFC0)] * 1000, cost=0.0)
    nmt = _nmt_after_reset(link)
    with pytest.raises(NmtError):
        nmt.wait_for_bootup(1.0)
    assert len(link.requests) <= 1.0 / GatewayNmt.BOOTUP_POLL_INTERVAL + 1
