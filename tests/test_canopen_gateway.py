"""The gateway's own rules for canopen, through the simulated EPOS4 (issue 17).

The same-body contract on both paths is ``test_canopen_contract.py``; here is
what only exists through the gateway, where a CAN bus would tell canopen
something the gateway never forwards: ``nmt.state`` from what the gateway
acknowledged and what answered, the probe before ``setup_402_state_machine``'s
PDO upload, ``wait_for_bootup`` without a reset, and the scanner's synchronous
search. Only the public API is used (``connect_node``), so these tests run
against any version of the adapter. The rule as data and ``wait_for_bootup``
on a scripted clock are in ``test_canopen_nmt_view.py``.
"""
from __future__ import annotations

from typing import Iterator

import canopen
import pytest
from canopen.profiles.p402 import BaseNode402

from epos_link import canopen_adapter
from epos_link.client import EposClient
from epos_link.simulator.transport import open_sim


@pytest.fixture
def client() -> Iterator[EposClient]:
    with EposClient(open_sim("sim://?drives=2")) as c:
        yield c


# --- through the gateway ---------------------------------------------------------------


def test_nmt_state_tells_the_truth_after_sdo_answers(client: EposClient) -> None:
    """Issue 17 finding 2: INITIALISING even after a hundred SDO answers."""
    node = canopen_adapter.connect_node(client, 2)
    assert node.nmt.state == "INITIALISING"  # unknown: never heard from
    for _ in range(100):
        node.sdo["Statusword"].raw
    assert node.nmt.state == "PRE-OPERATIONAL"
    again = canopen_adapter.connect_node(client, 2)  # the view belongs to the link
    assert again.nmt.state == "PRE-OPERATIONAL"
    node.nmt.state = "STOPPED"
    with pytest.raises(canopen.SdoAbortedError):  # a stopped node answers no SDO (Table 3-13)
        node.sdo["Statusword"].raw
    assert again.nmt.state == "STOPPED"
    node.nmt.state = "RESET"
    assert node.nmt.state == "INITIALISING"
    node.sdo["Statusword"].raw
    assert node.nmt.state == "PRE-OPERATIONAL"


def test_a_failed_request_is_no_answer(client: EposClient) -> None:
    node = canopen_adapter.connect_node(client, 5)  # nobody there: the gateway times out
    with pytest.raises(canopen.SdoAbortedError):
        node.sdo["Statusword"].raw
    assert node.nmt.state == "INITIALISING"


def test_the_gateway_itself_answered_when_connecting(client: EposClient) -> None:
    node = canopen_adapter.connect_node(client, 0)  # its node id was read from 2000h
    assert node.nmt.state == "PRE-OPERATIONAL"


def test_broadcast_through_network_nmt(client: EposClient) -> None:
    node = canopen_adapter.connect_node(client, 2)
    node.network.nmt.state = "OPERATIONAL"  # canopen's NmtMaster(0): all nodes
    assert node.nmt.state == "OPERATIONAL"
    assert node.network.nmt.state == "OPERATIONAL"
    node.network.nmt.state = "RESET"
    with pytest.raises(canopen_adapter.GatewayLimitationError, match="all nodes"):
        node.network.nmt.wait_for_bootup(1)
    node.nmt.wait_for_bootup(10)  # each node's own wait works after a broadcast reset
    assert node.nmt.state == "PRE-OPERATIONAL"


def test_a_refused_nmt_command_changes_no_state(client: EposClient) -> None:
    node = canopen_adapter.connect_node(client, 2)
    node.sdo["Statusword"].raw
    with pytest.raises(canopen.SdoCommunicationError, match="NMT"):
        node.nmt.state = "SLEEP"  # not an NMT command of guide Table 3-14
    assert node.nmt.state == "PRE-OPERATIONAL"


@pytest.mark.parametrize("node_id", [0, 2])
def test_setup_402_state_machine_with_its_defaults(client: EposClient, node_id: int) -> None:
    """Issue 17 finding 1: no NMT command, no SDO before: canopen's defaults."""
    n = canopen_adapter.connect_node(client, node_id, profile="402")
    n.setup_402_state_machine()
    assert n.tpdo[1].enabled and [v.index for v in n.tpdo[1]] == [0x6041]  # read by SDO
    n.state = "OPERATION ENABLED"  # ... and the state machine runs on SDO
    assert n.state == "OPERATION ENABLED"
    assert n.statusword == n.sdo["Statusword"].raw
    n.state = "SWITCH ON DISABLED"
    assert n.state == "SWITCH ON DISABLED"


def test_setup_on_a_node_this_adapter_stopped_keeps_canopens_assertion(client: EposClient) -> None:
    n = canopen_adapter.connect_node(client, 2, profile="402")
    assert isinstance(n, BaseNode402)
    n.nmt.state = "STOPPED"
    with pytest.raises(AssertionError):
        n.setup_402_state_machine()  # a stopped node does not answer SDO (guide Table 3-13)
    n.nmt.state = "PRE-OPERATIONAL"
    n.setup_402_state_machine()


def test_wait_for_bootup_without_a_reset_is_refused_by_name(client: EposClient) -> None:
    node = canopen_adapter.connect_node(client, 2)
    with pytest.raises(canopen_adapter.GatewayLimitationError, match="boot-up message"):
        node.nmt.wait_for_bootup(1)


def test_scanner_fills_nodes_and_the_nmt_view(client: EposClient) -> None:
    node = canopen_adapter.connect_node(client, 2)
    node.network.scanner.search(limit=3)
    assert node.network.scanner.nodes == [1, 2]  # at once: the probe is synchronous
    assert node.nmt.state == "PRE-OPERATIONAL"
