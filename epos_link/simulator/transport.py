"""``sim://``: the simulated EPOS4 in the same process, for fast tests and demos.

URL options: ``sim://?node_id=1&drives=2,3&segment=255&corrupt=0.05&drop=0&seed=1``.
Answers are available to :meth:`read` as soon as the request is written; the
optional faults are the same as the pty/TCP links'.
"""
from __future__ import annotations

import time
from collections import deque
from typing import Any, Optional
from urllib.parse import parse_qs, urlsplit

from ..errors import TransportError
from ..transports.base import Transport
from .core import Epos4Simulator
from .link_server import FaultInjector, LinkOptions


class SimTransport(Transport):
    def __init__(self, simulator: Epos4Simulator, *, options: Optional[LinkOptions] = None,
                 owns_simulator: bool = False, url: str = "sim://") -> None:
        self.simulator = simulator
        self.url = url
        self.faults = FaultInjector(options or LinkOptions())
        self._pending: deque[bytes] = deque()
        self._owns = owns_simulator
        self._closed = False

    def write(self, data: bytes) -> None:
        if self._closed:
            raise TransportError("sim:// transport is closed")
        for reply in self.simulator.receive(bytes(data)):
            reply = self.faults.apply(reply)
            if reply:
                self._pending.append(reply)

    def read(self, max_bytes: int, timeout: float) -> bytes:
        if self._closed:
            raise TransportError("sim:// transport is closed")
        if not self._pending:
            # Answers are produced on write, so nothing more will come; honour
            # the timeout anyway (a dropped answer must cost the caller its wait).
            time.sleep(max(0.0, timeout))
            return b""
        chunk = self._pending.popleft()
        if len(chunk) > max_bytes:
            self._pending.appendleft(chunk[max_bytes:])
            chunk = chunk[:max_bytes]
        return chunk

    def reset_input(self) -> None:
        self._pending.clear()

    def reopen(self) -> None:
        self._closed = False
        self._pending.clear()

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self._owns:
            self.simulator.close()


def _options(url: str) -> dict[str, str]:
    query = parse_qs(urlsplit(url).query)
    return {k: v[-1] for k, v in query.items()}


def open_sim(url: str, *, simulator: Optional[Epos4Simulator] = None, **_: Any) -> SimTransport:
    opts = _options(url)
    try:
        faults = LinkOptions(drop=float(opts.pop("drop", 0)), corrupt=float(opts.pop("corrupt", 0)),
                             seed=int(opts["seed"]) if "seed" in opts else None)
        opts.pop("seed", None)
        if simulator is not None:
            return SimTransport(simulator, options=faults, url=url)
        drives = [int(n) for n in opts.pop("drives", "").split(",") if n.strip()]
        sim = Epos4Simulator(int(opts.pop("node_id", 1)), drives,
                             segment_size=int(opts.pop("segment", 255)))
    except ValueError as exc:
        raise TransportError(f"bad sim:// URL {url!r}: {exc}") from None
    if opts:
        sim.close()
        raise TransportError(f"unknown sim:// options: {', '.join(sorted(opts))}")
    return SimTransport(sim, options=faults, owns_simulator=True, url=url)
