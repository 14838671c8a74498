"""The Channel Access server's network policy (issue 33), met by real clients:

* **The bridge's allow-list applies to CA clients**: the server listens on 127.0.0.2
  (``EPICS_CAS_INTF_ADDR_LIST``) and a pyepics client reaches it from 127.0.0.1 (the
  source Linux picks for loopback). With ``--allow 127.0.0.2/32`` its UDP search gets
  no answer, and a CA client that connects over TCP straight away (caproto's) is
  closed unanswered, each logged; with ``--allow 127.0.0.0/8`` the same clients read
  the record (so the refusal is the allow-list's).
* **Beacons** (``CA_PROTO_RSRV_IS_UP``) go to 127.0.0.1 while the server is on loopback
  only and ``EPICS_CAS_BEACON_ADDR_LIST`` is unset, and to the list when it is set.
"""
from __future__ import annotations

import select
import socket
import struct
import time
from typing import Dict, Iterator, List, Tuple

import pytest

from tests.epics_harness import Served, ca_env, free_port, no_client, run_client

REASON = no_client("epics")
pytestmark = pytest.mark.skipif(REASON is not None, reason=REASON or "")

SERVER = "127.0.0.2"
CA_PROTO_RSRV_IS_UP = 13  # Channel Access Protocol Specification, "CA_PROTO_RSRV_IS_UP"


@pytest.fixture(scope="module", params=["127.0.0.2/32", "127.0.0.0/8"],
                ids=["refused", "allowed"])
def bridge(request: pytest.FixtureRequest) -> Iterator[Tuple[Served, bool]]:
    env = ca_env()
    env["EPICS_CAS_INTF_ADDR_LIST"] = SERVER
    served = Served(["--simulate", "--axes", "1", "-v", "--allow", request.param], env=env)
    try:
        yield served, request.param == "127.0.0.0/8"
    finally:
        served.close()


def read_rbv(served: Served, how: str) -> Dict[str, object]:
    """TST:m1.RBV read by a client process: pyepics (libca) after a UDP search, or
    caproto's CA client straight over TCP to the server's address (as a client that
    knows where the server is; libca's TCP-only search, a name server, is a circuit
    caproto does not serve: "priority 1 does not match previously set priority")."""
    env = dict(served.env)
    port = env["EPICS_CA_SERVER_PORT"]
    if how == "udp":
        env.update(EPICS_CA_ADDR_LIST=SERVER, EPICS_CA_AUTO_ADDR_LIST="NO")
        return run_client("""
            import json, epics
            print(json.dumps(dict(rbv=epics.caget("TST:m1.RBV", timeout=3.0))))
            """, env)
    return run_client(f"""
        import json
        from caproto.sync import client
        client.search = lambda *args, **kw: ("{SERVER}", {port})  # no UDP: TCP at once
        try:
            rbv = float(client.read("TST:m1.RBV", timeout=3.0, repeater=False).data[0])
        except Exception as exc:
            rbv = None
            print(repr(exc))
        print(json.dumps(dict(rbv=rbv)))
        """, env)


@pytest.mark.parametrize("how", ["udp", "tcp"])
def test_the_allow_list_applies_to_ca_searches_and_connections(
        bridge: Tuple[Served, bool], how: str) -> None:
    served, allowed = bridge
    out = read_rbv(served, how)
    if allowed:
        assert out["rbv"] == pytest.approx(0.0), out  # the same client, let in
        return
    assert out["rbv"] is None, out  # nothing answered
    said = {"udp": "ignoring CA searches from 127.0.0.1: not in the allow-list",
            "tcp": "refused CA connection from ('127.0.0.1'"}[how]
    deadline = time.monotonic() + 10
    while said not in "".join(served.output):
        assert time.monotonic() < deadline, "".join(served.output)
        time.sleep(0.05)


def beacons(socks: List[socket.socket], seconds: float) -> List[List[Tuple[int, int]]]:
    """(server port, beacon id) of the CA beacons each socket receives meanwhile."""
    got: List[List[Tuple[int, int]]] = [[] for _ in socks]
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        ready, _, _ = select.select(socks, [], [], 0.1)
        for sock in ready:
            data = sock.recv(1024)
            # CA header: command, payload size, data type, count, parameter 1, 2 (all
            # big-endian); RSRV_IS_UP carries the server's TCP port as its count
            # and the beacon id as parameter 1.
            command, _, _, port, beacon_id, _ = struct.unpack(">HHHHII", data[:16])
            if command == CA_PROTO_RSRV_IS_UP:
                got[socks.index(sock)].append((port, beacon_id))
    return got


@pytest.mark.parametrize("listed", [False, True], ids=["loopback default", "listed"])
def test_beacons_go_to_loopback_unless_a_beacon_address_list_says_where(
        listed: bool) -> None:
    env = ca_env()
    port = free_port()
    env["EPICS_CAS_BEACON_PORT"] = str(port)
    if listed:
        env.update(EPICS_CAS_BEACON_ADDR_LIST="127.0.0.3",
                   EPICS_CAS_AUTO_BEACON_ADDR_LIST="NO")
    socks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(2)]
    try:
        # Bound before the server starts: its first beacons come at once (caproto:
        # 0.02 s, doubling), and wait in the sockets' buffers.
        socks[0].bind(("127.0.0.1", port))
        socks[1].bind(("127.0.0.3", port))
        served = Served(["--simulate", "--axes", "1"], env=env)
        try:
            at_loopback, at_listed = beacons(socks, 2.0)
        finally:
            served.close()
    finally:
        for sock in socks:
            sock.close()
    server_port = int(env["EPICS_CA_SERVER_PORT"])
    expected, nothing = (at_listed, at_loopback) if listed else (at_loopback, at_listed)
    assert expected and all(p == server_port for p, _ in expected), (at_loopback, at_listed)
    assert nothing == [], (at_loopback, at_listed)
