"""Fail-fast glue for one bus: the health record, the probes, the refusals.

:class:`tcp_bridge.bus.health.BusHealth` holds the policy (pure, documented
there); this module connects it to the I/O: :class:`BusGuard` gives each
axis's :class:`~tcp_bridge.bus.sdo.SdoPort` its node's
:class:`~tcp_bridge.bus.health.NodeHealth`, in which the port records every
transfer's outcome, answers :meth:`BusGuard.refusal` for the engine before a
job is queued and again when its turn comes (so nothing queued during an
outage reaches the device), and runs the due probes on the bus's worker
thread (:meth:`BusGuard.maintain`, called by :class:`tcp_bridge.bus.workers.BusWorker`
between jobs and while idle), and probes a link a job found silent before
that job's reply goes out (:meth:`BusGuard.settle`).

A probe reads object 1000h/00h (device type, mandatory for every CANopen
device: CiA 301 7.5.2.1): of the node for a silent node; for the bus's device,
the backend's own ``probe()`` if it has one (``epos``: the EPOS4 itself,
node 0 on its link, with a short timeout and no retry), else of the bus's first
node, where any answer, an abort included, proves the link works. A garbled
answer to a probe is tried again, as a transfer's is
(:func:`~tcp_bridge.bus.sdo.retry_garbled`). Probes
bypass the axes' SdoPorts, so they never feed the CiA 402 state of an axis.
"""
from __future__ import annotations

import logging
from typing import Any, Callable, Mapping, Optional

from ..errors import SilentLink
from .health import BusHealth, Change, NodeHealth, Silence, Target
from .sdo import _is_device_error, retry_garbled, silence_of

log = logging.getLogger(__name__)

DEVICE_TYPE = 0x1000  # CiA 301 7.5.2.1, mandatory in every CANopen device


def log_change(change: Change, describe: Optional[Callable[[str], str]] = None) -> None:
    """The ``on_change`` of a bridge's :class:`BusHealth`: each change of state, one line.

    ``describe`` (a backend's ``describe_silence``) words a silent bus's device:
    its URL and what to check, as ``tcp-bridge check`` says it."""
    if change.silent and change.device and describe is not None:
        log.warning("bus %s: %s; its commands answer NAK at once until a probe gets an "
                    "answer", change.link.split(":", 1)[0].removeprefix("bus "),
                    describe(change.why))
    elif change.silent:
        log.warning("%s silent (%s): its commands answer NAK at once until a probe gets an "
                    "answer", change.link, change.why)
    else:
        log.warning("%s answers again after %.1f s silent; its commands are served",
                    change.link, change.duration)


class BusGuard:
    """Fail-fast for one bus: its :class:`BusHealth` and the probes of its links."""

    def __init__(self, health: BusHealth, nodes: Mapping[int, Any],
                 link_probe: Optional[Callable[[], Any]] = None) -> None:
        self.health = health
        self.nodes = dict(nodes)  # node id -> node (canopen SDO interface)
        self._link_probe = link_probe

    def node(self, node_id: int) -> NodeHealth:
        """For the SdoPort (and the axis) of ``node_id``: its node's health."""
        return NodeHealth(self.health, node_id)

    def refusal(self, node_id: Optional[int]) -> Optional[SilentLink]:
        reason = self.health.refusal(node_id)  # names its link: "bus can1: device silent ..."
        return SilentLink(reason) if reason else None

    def guarded(self, job: Callable[[], Any], node_id: Optional[int], *,
                check: bool = True) -> Callable[[], Any]:
        """``job`` as the bus worker runs it: refused when its turn comes if its link went
        silent while it waited (unless ``check`` is False: stops), and followed by
        :meth:`settle`, before its reply goes out."""
        def run() -> Any:
            if check:
                refusal = self.refusal(node_id)
                if refusal is not None:
                    raise refusal
            try:
                return job()
            finally:
                self.settle()
        return run

    def settle(self) -> None:
        """Probe the links a job found silent: declare them silent, or clear them."""
        for _ in range(2):  # the device first; then, if it answers, the suspect nodes
            targets = self.health.suspects()
            if not targets:
                return
            for target in targets:
                silence, why = self._probe(target)
                self.health.probed(target, silence, why)

    def maintain(self) -> Optional[float]:
        """Run the periodic probes that are due; seconds until the next (None: none)."""
        for target in self.health.due():
            silence, why = self._probe(target)
            self.health.probed(target, silence, why)
        return self.health.next_due()

    def _probe(self, target: Target) -> "tuple[Optional[Silence], str]":
        def probe() -> None:
            if target is not None:
                self.nodes[target].sdo.upload(DEVICE_TYPE, 0)
            elif self._link_probe is not None:
                self._link_probe()
            elif self.nodes:
                next(iter(self.nodes.values())).sdo.upload(DEVICE_TYPE, 0)

        try:
            retry_garbled(probe)  # a garbled answer is no silence (tcp_bridge.bus.sdo)
        except Exception as exc:
            if not _is_device_error(exc):
                # A bug, not a device answer: keep the link closed and say so.
                log.exception("bus %s: probe of %s failed", self.health.bus,
                              "the device" if target is None else f"node {target}")
                return (Silence.LINK if target is None else Silence.NODE), f"probe failed: {exc}"
            return silence_of(exc), str(exc)
        return None, ""
