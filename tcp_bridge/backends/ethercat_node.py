"""A slave of an ``ethercat`` bus as a node with canopen's interface, and its errors.

What goes by process data and what by CoE SDO, the errors, and the cyclic
set-point API are described in :mod:`tcp_bridge.backends.ethercat` (module
docstring); the lock and the cycle in :mod:`tcp_bridge.backends.ethercat_cycle`.
"""
from __future__ import annotations

import logging
from typing import Any, Callable, Optional

from canopen.nmt import NmtError
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from ..bus.sdo import object_type
from ..errors import BusUnavailable
from . import ethercat_pdo as pdo
from .ethercat_cycle import INIT

log = logging.getLogger("tcp_bridge.backends.ethercat")

# The longest a transfer waits for another one to finish, beyond its own sdo_timeout
# (a store of parameters, 1010h, takes seconds on an EPOS4).
MAILBOX_WAIT = 10.0


def _desc(exc: BaseException) -> str:
    try:  # pysoem's PacketError.desc is a lookup that raises KeyError for unknown codes
        return str(getattr(exc, "desc", ""))
    except Exception:
        return ""


class SlaveUnreachable(SdoCommunicationError):  # type: ignore[misc]
    """The slave is lost or out of OP, or its mailbox gave no answer: a silent node."""


class LinkDown(BusUnavailable):
    """No frame comes back on the card: the bus's device is silent."""


class EthercatNode:
    """One slave; ``sdo`` is itself (canopen's ``upload``/``download``)."""

    def __init__(self, backend: Any, position: int) -> None:
        self.id = position
        self._bus = backend
        self.sdo = self
        self.nmt = _Nmt(self)
        self.cyclic: Optional[Any] = None  # cyclic = "csp": the bus's CycleSender

    @property
    def _layout(self) -> Optional[pdo.Layout]:  # None: the slave's mapping is unknown
        return self._bus.layouts.get(self.id)

    def _reachable(self) -> Any:
        cycle = self._bus.cycle
        if cycle.link_down:
            raise LinkDown(f"no EtherCAT frame comes back on {self._bus.interface}")
        slave = cycle.slaves.get(self.id)
        if slave is None:
            raise SlaveUnreachable(f"no slave at position {self.id} on {self._bus.interface} "
                                   f"({len(cycle.slaves)} found)")
        why = cycle.lost.get(self.id)
        if why is not None:
            raise SlaveUnreachable(why)
        return slave

    def upload(self, index: int, subindex: int) -> bytes:
        slave = self._reachable()
        layout, cycle = self._layout, self._bus.cycle
        if layout is not None and (index, subindex) in layout.inputs:
            if not cycle.wait_cycles(1, self._bus.sdo_timeout + 10 * cycle.period):
                raise SlaveUnreachable(f"slave {self.id}: no process-data cycle completed")
            self._reachable()  # that cycle may have found it lost
            entry = layout.inputs[(index, subindex)]
            return cycle.inputs[self.id][entry.offset:entry.offset + entry.size]
        if layout is not None and (index, subindex) in layout.outputs:
            entry = layout.outputs[(index, subindex)]
            with cycle.lock:
                return bytes(cycle.outputs[self.id][entry.offset:entry.offset + entry.size])
        return bytes(self._mailbox(lambda: slave.sdo_read(index, subindex, ca=False,
                                                         release_gil=True)))

    def download(self, index: int, subindex: int, data: bytes,
                 force_segment: bool = False) -> None:
        slave = self._reachable()
        layout, cycle = self._layout, self._bus.cycle
        if layout is not None and (index, subindex) in layout.outputs:
            entry = layout.outputs[(index, subindex)]
            if len(data) != entry.size:  # what an SDO would answer (CiA 301 7.2.4.3.17)
                raise SdoAbortedError(0x06070010)
            with cycle.lock:
                pdo.put(cycle.outputs[self.id], entry, bytes(data))
                if self._bus.hold is not None:
                    self._bus.hold.commanded(self.id, (index, subindex))  # ethercat_hold
            if not cycle.wait_cycles(2, self._bus.sdo_timeout + 10 * cycle.period):
                raise SlaveUnreachable(f"slave {self.id}: no process-data cycle carried it")
            self._reachable()
            return
        self._mailbox(lambda: slave.sdo_write(index, subindex, bytes(data), ca=False,
                                              release_gil=True))

    def _mailbox(self, transfer: Callable[[], Any]) -> Any:
        """A CoE transfer, under the mailbox lock, not the cycle's (:mod:`.ethercat_cycle`
        rule 1); pysoem's errors become the backend's (module docstring)."""
        soem, cycle = self._bus.soem, self._bus.cycle
        if not cycle.mailbox.acquire(timeout=MAILBOX_WAIT + self._bus.sdo_timeout):
            raise SlaveUnreachable(f"slave {self.id}: the mailbox stayed busy with another "
                                   f"transfer for {MAILBOX_WAIT + self._bus.sdo_timeout:g} s")
        try:
            return self._twice(transfer)
        except soem.SdoError as exc:
            raise SdoAbortedError(int(exc.abort_code)) from exc
        except soem.WkcError as exc:
            self._bus.cycle._check = True  # the next cycle reads the slaves' states
            raise SlaveUnreachable(f"slave {self.id}: its mailbox did not answer "
                                   f"(working counter {getattr(exc, 'wkc', '?')})") from exc
        except (soem.MailboxError, soem.PacketError) as exc:
            raise SlaveUnreachable(f"slave {self.id}: mailbox error "
                                   f"{getattr(exc, 'error_code', '?')} "
                                   f"{_desc(exc)}".rstrip()) from exc
        finally:
            cycle.mailbox.release()

    def _twice(self, transfer: Callable[[], Any]) -> Any:
        """A transfer whose frames got no answer (SOEM's working counter 0, or -2 when
        only other frames came back within its wait) is made once more, unless the slave
        is known lost. A frame lost or late on the line (a loaded host, noise) is not a
        silent slave: SOEM repeats a lost *reply* itself (the mailbox repeat request,
        ETG.1000.4 SM1 "repeat") but not a lost request. Our transfers are single object
        writes and reads, so a second one does what the first would have; a slave that
        answered the first after all has its stale reply dropped by SOEM before the
        second (ecx_SDOread/ecx_SDOwrite empty the mailbox first). (Under load a suite
        saw 'write 0x6083/0 failed: its mailbox did not answer (working counter -2)'.)"""
        cycle = self._bus.cycle
        try:
            return transfer()
        except self._bus.soem.WkcError as exc:
            if self.id in cycle.lost or cycle.link_down:
                raise
            log.info("bus %s: slave %d: a CoE transfer got no answer (working counter %s): "
                     "made once more", self._bus.name, self.id, getattr(exc, "wkc", "?"))
        return transfer()

    # -- cyclic set-points (module docstring, "Cyclic set-points") ------------------------

    def pdo_write(self, index: int, subindex: int, value: int) -> None:
        """Put ``value`` into the output image now (sent with the next cycle); KeyError
        if the slave does not map the object into its outputs."""
        layout = self._layout
        if layout is None or (index, subindex) not in layout.outputs:
            raise KeyError(f"slave {self.id} maps no 0x{index:04X}/{subindex} in its outputs")
        entry = layout.outputs[(index, subindex)]
        data = int(value).to_bytes(entry.size, "little", signed=object_type(index, subindex)[1])
        with self._bus.cycle.lock:
            pdo.put(self._bus.cycle.outputs[self.id], entry, data)
            if self._bus.hold is not None:
                self._bus.hold.commanded(self.id, (index, subindex))  # ethercat_hold

    def cyclic_target(self, position: int) -> None:
        """The CSP set-point of this cycle: target position 607Ah in the outputs."""
        self.pdo_write(0x607A, 0, position)

    def pdo_read(self, index: int, subindex: int = 0) -> int:
        """The newest value of a mapped object (inputs first, else outputs); KeyError
        if it is not mapped. Does not wait for a cycle."""
        layout, cycle = self._layout, self._bus.cycle
        signed = object_type(index, subindex)[1]
        if layout is not None and (index, subindex) in layout.inputs:
            return pdo.get(cycle.inputs[self.id], layout.inputs[(index, subindex)], signed)
        if layout is not None and (index, subindex) in layout.outputs:
            with cycle.lock:
                return pdo.get(cycle.outputs[self.id], layout.outputs[(index, subindex)], signed)
        raise KeyError(f"slave {self.id} maps no 0x{index:04X}/{subindex}")


class _Nmt:
    """canopen's NmtMaster as far as EtherCAT has it (module docstring, chosen)."""

    def __init__(self, node: EthercatNode) -> None:
        self._node = node

    @property
    def state(self) -> str:
        cycle = self._node._bus.cycle
        slave = cycle.slaves.get(self._node.id)
        return "OPERATIONAL" if slave is not None and self._node.id not in cycle.lost else "STOPPED"

    @state.setter
    def state(self, value: str) -> None:
        node, cycle = self._node, self._node._bus.cycle
        slave = cycle.slaves.get(node.id)
        if value == "OPERATIONAL":
            with cycle.lock:
                cycle._check = True  # the next cycle looks at it, and asks for OP if needed
            return
        if not value.startswith("RESET"):
            raise NmtError(f"EtherCAT has no NMT {value.lower()} (slave {node.id})")
        if slave is None:
            raise SlaveUnreachable(f"no slave at position {node.id}")
        # Chosen (module docstring of ethercat): INIT and back to OP by the recovery.
        with cycle.lock:
            slave.state = INIT
            slave.write_state()
            cycle.lost[node.id] = f"slave {node.id} was reset by the bridge (INIT, back to OP)"
            cycle._check = True
