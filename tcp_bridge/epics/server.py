"""The Channel Access server of the bridge (``serve --epics PREFIX``), on caproto.

A caproto asyncio :class:`caproto.asyncio.server.Context` on the bridge's own event
loop, with three changes of policy (the rest is caproto's):

* **The allow-list** of the bridge (``--allow``, ``[bridge] allow``; default loopback)
  applies to CA clients too: a TCP connection from elsewhere is closed at once,
  unanswered, and logged with its address (as :mod:`tcp_bridge.server` does); a UDP
  search from elsewhere gets no answer (logged once per address, at most
  :data:`MAX_LOGGED` addresses).
* **Loopback unless told**: the interfaces are EPICS_CAS_INTF_ADDR_LIST, else
  127.0.0.1 (:func:`tcp_bridge.epics.names.interfaces`); a non-loopback interface
  without an allow-list is refused at start-up, as ``--bind`` is.
* **Beacons** go to 127.0.0.1 while the server is on loopback only and
  EPICS_CAS_BEACON_ADDR_LIST is unset (:func:`tcp_bridge.epics.names.beacon_addresses`).

:func:`open_epics` starts the records (one read each: VAL = RBV) and the server, and
returns once it listens.
"""
from __future__ import annotations

import asyncio
import logging
import os
from typing import Any, List, Mapping, Optional, Sequence, Set, Tuple

from caproto import CaprotoError
from caproto.asyncio.server import Context
from caproto.asyncio.utils import _create_udp_socket

from . import PutRefused, names
from .axis import IDLE_PERIOD, MOVING_PERIOD, AxisRecord
from .pvs import RecordChannels, build
from ..access import Network, is_allowed
from ..tables.axes import ConfigError
from ..tasks import cancel_and_wait

log = logging.getLogger(__name__)

MAX_LOGGED = 64  # refused search addresses logged (a bound: one line each)
START_TIMEOUT = 10.0  # s for caproto to bind its sockets


class _RefusedPuts(logging.Filter):
    """Drops caproto's "Invalid write request" record (with its traceback) for a put the
    bridge refused on purpose (:class:`~tcp_bridge.epics.PutRefused`): the record has
    logged one line for it already. caproto still answers the put with ECA_PUTFAIL
    (``caproto.server.common``, ``handle_write``). Any other exception keeps its
    traceback: that one is a bug."""

    def filter(self, record: logging.LogRecord) -> bool:
        exc = record.exc_info[1] if record.exc_info else None
        return not isinstance(exc, PutRefused)


REFUSED_PUTS = _RefusedPuts()


class BridgeContext(Context):  # type: ignore[misc]
    """caproto's server context with the bridge's allow-list and beacon addresses."""

    def __init__(self, pvdb: Any, interfaces: List[str], allow: Sequence[Network],
                 beacons: Optional[List[Tuple[str, int]]]) -> None:
        super().__init__(pvdb, interfaces)
        logging.getLogger("caproto.circ").addFilter(REFUSED_PUTS)  # once: a set of one
        self.allow = tuple(allow)
        self.beacons = beacons
        self.refused: Set[str] = set()

    async def tcp_handler(self, client: Any, addr: Any) -> None:
        if not is_allowed(addr, self.allow):
            log.warning("EPICS: refused CA connection from %s: not in the allow-list", addr)
            client.writer.close()
            return
        await super().tcp_handler(client, addr)

    async def _broadcaster_recv_datagram(self, bytes_received: bytes, address: Any) -> None:
        if not is_allowed(address, self.allow):
            if len(self.refused) < MAX_LOGGED and address[0] not in self.refused:
                self.refused.add(address[0])
                log.warning("EPICS: ignoring CA searches from %s: not in the allow-list",
                            address[0])
            return
        await super()._broadcaster_recv_datagram(bytes_received, address)

    async def broadcast_beacon_loop(self) -> None:
        if self.beacons is not None:
            old: Any = getattr(self, "beacon_socks")
            for _, transport in old.values():
                transport.transport.close()
            self.beacon_socks = {}
            for address in self.beacons:
                self.beacon_socks[address] = (address[0], _Beacon(address))
        await super().broadcast_beacon_loop()


class _Beacon:
    """A beacon destination: ``sendto`` on an unconnected socket, as EPICS base's rsrv
    sends them. Nobody listening (no CA repeater on this host) is normal, not an error
    worth caproto's traceback each time: the send is dropped."""

    def __init__(self, address: Tuple[str, int]) -> None:
        self.address = address
        self.sock = _create_udp_socket()

    async def send(self, data: bytes) -> None:
        try:
            self.sock.sendto(data, self.address)
        except OSError as exc:
            log.debug("EPICS: beacon to %s:%d not sent: %s", *self.address, exc)

    def close(self) -> None:
        self.sock.close()


class EpicsServer:
    """The records of every axis and the CA server that serves them."""

    def __init__(self, engine: Any, prefix: str, *, allow: Sequence[Network],
                 environ: Optional[Mapping[str, str]] = None,
                 periods: Optional[Mapping[str, float]] = None) -> None:
        env = dict(os.environ if environ is None else environ)
        self.interfaces = names.interfaces(env)
        names.server_port(env)  # a bad EPICS_CA_SERVER_PORT is one line, exit 2
        if not names.loopback_only(self.interfaces) and tuple(allow) == _loopback():
            raise ConfigError(f"EPICS_CAS_INTF_ADDR_LIST {' '.join(self.interfaces)} serves "
                              "other hosts: say which with --allow CIDR (or [bridge] allow)")
        self.beacons = names.beacon_addresses(env, self.interfaces)
        axes = [(addr, getattr(engine.table.axes[addr], "epics_name", None))
                for addr in sorted(engine.axes)]
        self.names = names.record_names(prefix, axes)
        p = dict(periods or {})
        self.records = [AxisRecord(engine, addr,
                                   moving_period=p.get("moving_period", MOVING_PERIOD),
                                   idle_period=p.get("idle_period", IDLE_PERIOD))
                        for addr, _ in self.names]
        pvdb, self.channels = build([(r, n) for r, (_, n) in zip(self.records, self.names)])
        self.context = BridgeContext(pvdb, self.interfaces, allow, self.beacons)
        for channels in self.channels:
            channels.context = self.context
        self._task: Optional["asyncio.Task[None]"] = None

    @property
    def port(self) -> int:
        return int(self.context.port)

    def channels_of(self, addr: int) -> RecordChannels:
        return next(c for c in self.channels if c.record.addr == addr)

    async def start(self) -> "EpicsServer":
        for record in self.records:
            await record.start()
        started = asyncio.Event()

        async def hook(_: Any) -> None:
            started.set()

        self._task = asyncio.ensure_future(self.context.run(startup_hook=hook))
        waiter = asyncio.ensure_future(started.wait())
        done, _ = await asyncio.wait({self._task, waiter}, timeout=START_TIMEOUT,
                                     return_when=asyncio.FIRST_COMPLETED)
        if self._task in done:
            waiter.cancel()
            exc = self._task.exception()
            await self.close()
            raise OSError(f"cannot serve Channel Access: {exc}")
        if waiter not in done:
            waiter.cancel()
            await self.close()
            raise OSError(f"Channel Access server did not start within {START_TIMEOUT:g} s")
        return self

    def describe(self) -> str:
        where = ", ".join(f"{i}:{self.port}" for i in self.interfaces)
        return (f"EPICS Channel Access on {where} (UDP {self.context.ca_server_port}); "
                f"motor records {', '.join(n for _, n in self.names)}")

    async def close(self) -> None:
        for record in self.records:
            await record.close()
        if self._task is not None:
            if await cancel_and_wait([self._task], 5.0):
                log.warning("EPICS: the CA server still runs 5 s after it was cancelled")
            self._task = None


def _loopback() -> Tuple[Network, ...]:
    from ..access import LOOPBACK
    return LOOPBACK


async def open_epics(engine: Any, prefix: str, *, allow: Sequence[Network],
                     periods: Optional[Mapping[str, float]] = None) -> EpicsServer:
    """Build and start the CA server of ``engine``'s axes (see the module docstring)."""
    try:
        return await EpicsServer(engine, prefix, allow=allow, periods=periods).start()
    except CaprotoError as exc:
        raise OSError(str(exc)) from None
