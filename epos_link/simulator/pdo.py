"""Transmit PDOs of a simulated drive, configured like an EPOS4's (0x1800/0x1A00 ...).

The mapping rules below are shared with the receive PDOs
(:func:`install_mapping_rules`; :mod:`epos_link.simulator.rpdo`).

Objects (CiA 301 V4.2 7.5.2.37 TPDO communication, 7.5.2.38 TPDO mapping;
guide 3.3.3.1 and Figure 3-23 for the default COB-IDs):

* 18xxh: sub 1 COB-ID (bit 31 = 1: the PDO is not valid), sub 2 transmission
  type, sub 3 inhibit time in 100 us, sub 5 event timer in ms;
* 1Axxh: sub 0 number of mapped objects, subs 1..8 ``index << 16 | subindex
  << 8 | length in bits``.

Rules for an SDO download (abort codes of CiA 301 Table 22):

* the mapping (1Axxh any sub) can be changed only while the PDO is not valid,
  and subs 1..8 only while sub 0 is 0 (the procedure of 7.5.2.38):
  06010000h "unsupported access" otherwise (**chosen**: the code CiA 301
  leaves to the device);
* a mapped object must exist (06020000h), be mappable by the EDS
  (``PDOMapping=1``, else 06040041h) and be mapped with its own length; all
  mapped objects together fit 64 bits (06040042h);
* the CAN identifier of a valid PDO cannot change (06090030h).

Transmission, with what is **chosen** where CiA 301 leaves it to the device:

* only in NMT Operational (guide 3.3.3.5, Table 3-13), only a valid PDO, and
  only the event-driven transmission types 254/255; the synchronous types
  (0..240) need a SYNC producer, which the simulator does not have, so they
  are not sent (chosen);
* on change: a PDO is sent when its data differ from the last sent, but not
  sooner than the inhibit time after it; at least every event timer period
  (if not 0); and at once on entering Operational (chosen);
* the drive samples its mapped objects every ``tick`` seconds (default 2 ms,
  chosen: a real EPOS4 samples in its control cycle); a change is sent up to
  one tick late. A drive whose PDO data did not change at the last sample, and
  that got no SDO write since, is sampled only every ``QUIET`` seconds (10 ms)
  and when an event timer is due (chosen, to keep idle drives cheap: what
  changes at rest without a write, such as the end of the self test or a fault
  injected through the Python API, is sent up to QUIET + GRID + one tick
  late, about 17 ms). These samples fall on a common grid of the clock
  (``GRID``, 5 ms), so that the ticker wakes once for all quiet drives, not
  once for each; so does an event timer: its PDO goes out at the grid instant
  nearest to the end of its period (plus the ticker's own lateness), and the
  next period ends one period after the end of this one, not after its
  sending: a period that is a multiple of 5 ms (the bridge's 50 ms) is kept
  to the ticker's lateness, any other within 5 ms, and on average exactly
  (chosen); a change sent starts the period again (CiA 301 7.2.2.2.1);
* sampled and sent under the drive's lock: a PDO received after the answer to
  an SDO write shows the drive after that write (the order the bridge's PDO
  reads rely on, ``tcp_bridge.pdo_status``).

``refuse_mapping = True`` makes every mapping entry abort 06040041h, as a
drive whose firmware does not allow those objects in a PDO (tests).
"""
from __future__ import annotations

import math
from functools import partial
import threading
import time
from dataclasses import dataclass
from typing import Callable, Dict, Final, Iterable, List, Optional, Tuple

import can
from canopen.objectdictionary import ODVariable
from canopen.sdo import SdoAbortedError

from .od import ABORT_NO_OBJECT, ABORT_RANGE, ObjectStore, Value

ABORT_UNSUPPORTED: Final = 0x06010000
ABORT_NOT_MAPPABLE: Final = 0x06040041
ABORT_MAP_LENGTH: Final = 0x06040042
NOT_VALID: Final = 1 << 31
COB_ID_MASK: Final = 0x1FFFFFFF
EVENT_DRIVEN: Final = frozenset({254, 255})
TICK: Final = 0.002  # seconds between samples (chosen, see the module docstring)
MAX_ENTRIES: Final = 8
QUIET: Final = 0.01  # seconds between samples of a drive at rest (chosen, see above)
GRID: Final = 0.005  # seconds: quiet drives are sampled at multiples of it (see above)
IDLE_WAIT: Final = 0.5  # seconds the ticker sleeps while no drive is Operational (a bound only)


@dataclass
class _Sent:
    data: Optional[bytes] = None
    at: float = float("-inf")
    due: float = float("-inf")  # when the event timer wants it sent again (exact)


@dataclass(frozen=True)
class _Plan:
    """One valid, event-driven TPDO as configured: what to sample and when to send."""

    number: int
    cob_id: int
    inhibit: float  # seconds
    timer: float  # seconds, 0: no event timer
    objects: Tuple[Tuple[ODVariable, int], ...]  # (variable, bytes)



# -- the mapping rules, shared with the receive PDOs (epos_link.simulator.rpdo) ------------

def mapping_subs(store: ObjectStore, index: int) -> List[int]:
    return sorted(getattr(store.od[index], "subindices", {}))


def mapped_variable(store: ObjectStore, entry: int) -> ODVariable:
    """The object a mapping entry (index << 16 | subindex << 8 | bits) names, or 06020000h."""
    try:
        return store.variable(entry >> 16, (entry >> 8) & 0xFF)
    except SdoAbortedError:
        raise SdoAbortedError(ABORT_NO_OBJECT) from None


def install_mapping_rules(store: ObjectStore, com: int, mapping: int, changed: Callable[[], None],
                          refuse: Callable[[], bool], *, receive: bool = False) -> None:
    """The SDO download rules of the module docstring on one PDO's communication (``com``)
    and mapping (``mapping``) objects; ``changed()`` runs before any accepted change is
    stored. A receive PDO maps only objects that can be written (CiA 301 7.5.2.36:
    an RPDO writes its objects), else 06040041h."""

    def check_cob_id(value: Value) -> None:
        assert isinstance(value, int)
        changed()
        old = store.get_int(com, 1)
        if not old & NOT_VALID and not value & NOT_VALID and (old ^ value) & COB_ID_MASK:
            raise SdoAbortedError(ABORT_RANGE)  # a valid PDO keeps its identifier

    def check_map(sub: int, value: Value) -> None:
        assert isinstance(value, int)
        changed()
        if not store.get_int(com, 1) & NOT_VALID:
            raise SdoAbortedError(ABORT_UNSUPPORTED)  # destroy the PDO first
        if sub == 0:
            if value > MAX_ENTRIES or value > len(mapping_subs(store, mapping)) - 1:
                raise SdoAbortedError(ABORT_MAP_LENGTH)
            entries = [store.get_int(mapping, s) for s in range(1, value + 1)]
            if sum(e & 0xFF for e in entries) > 64:
                raise SdoAbortedError(ABORT_MAP_LENGTH)
            return
        if store.get_int(mapping, 0) != 0:
            raise SdoAbortedError(ABORT_UNSUPPORTED)  # number of entries first set to 0
        if value == 0:
            return  # an empty entry
        if refuse():
            raise SdoAbortedError(ABORT_NOT_MAPPABLE)
        var = mapped_variable(store, value)
        if not var.pdo_mappable or len(var) != value & 0xFF or (receive and not var.writable):
            raise SdoAbortedError(ABORT_NOT_MAPPABLE)

    store.add_write_hook(com, 1, check_cob_id)
    for sub in mapping_subs(store, com):
        if sub != 1:
            store.add_write_hook(com, sub, lambda v: changed())
    for sub in mapping_subs(store, mapping):
        store.add_write_hook(mapping, sub, partial(check_map, sub))


class TransmitPdos:
    """The TPDOs of one drive's object store: mapping rules and what is due to send."""

    def __init__(self, store: ObjectStore) -> None:
        self.store = store
        self.refuse_mapping = False
        self.numbers: Tuple[int, ...] = tuple(
            n for n in range(512) if 0x1800 + n in store.od and 0x1A00 + n in store.od)
        self._sent: Dict[int, _Sent] = {n: _Sent() for n in self.numbers}
        self._plans: Optional[Tuple[_Plan, ...]] = None  # None: read the objects again
        self._next_sample = float("-inf")  # a quiet drive is sampled again at this time
        for n in self.numbers:
            install_mapping_rules(store, 0x1800 + n, 0x1A00 + n, self._changed,
                                  lambda: self.refuse_mapping)

    def _changed(self) -> None:
        self._plans = None  # the hook runs before the value is stored: plan again next time

    def touch(self) -> None:
        """An SDO write reached the drive: sample at the next tick."""
        self._next_sample = float("-inf")

    def wants_sample(self, now: float) -> bool:
        return now >= self._next_sample

    @property
    def next_sample(self) -> float:
        """When this drive wants to be sampled again (-inf: at the next tick)."""
        return self._next_sample

    # -- transmission ------------------------------------------------------------------

    def reset(self) -> None:
        """Not Operational, or reset (the objects may be back at their defaults):
        nothing sent; on entering Operational every PDO goes out."""
        self._plans = None
        self._next_sample = float("-inf")
        for sent in self._sent.values():
            sent.data, sent.at, sent.due = None, float("-inf"), float("-inf")

    def _plan(self) -> Tuple[_Plan, ...]:
        get = self.store.get_int
        plans = []
        for n in self.numbers:
            cob_id = get(0x1800 + n, 1)
            if cob_id & NOT_VALID or get(0x1800 + n, 2) not in EVENT_DRIVEN:
                continue
            entries = [get(0x1A00 + n, sub) for sub in range(1, get(0x1A00 + n, 0) + 1)]
            objects = tuple((mapped_variable(self.store, e), (e & 0xFF) // 8) for e in entries if e)
            plans.append(_Plan(n, cob_id & COB_ID_MASK, get(0x1800 + n, 3) * 1e-4,
                               get(0x1800 + n, 5) * 1e-3, objects))
        return tuple(plans)

    def due(self, now: float) -> List[Tuple[int, bytes]]:
        """(COB-ID, data) of every PDO to send at ``now``; the caller holds the drive's lock
        and has brought the drive model up to ``now``."""
        if self._plans is None:
            self._plans = self._plan()
        out: List[Tuple[int, bytes]] = []
        get = self.store.get
        quiet, next_sample = True, math.ceil((now + QUIET) / GRID) * GRID
        for plan in self._plans:
            data = b"".join(var.encode_raw(get(var.index, var.subindex))[:size]
                            for var, size in plan.objects)
            sent = self._sent[plan.number]
            quiet = quiet and data == sent.data
            changed = data != sent.data and now - sent.at >= plan.inhibit
            timed = plan.timer > 0 and now >= _on_grid(sent.due)
            if changed or timed:
                # A change starts the period again; the timer's own sending keeps
                # to its schedule, so that the grid never makes the period drift.
                due = now + plan.timer if changed or sent.due + plan.timer <= now \
                    else sent.due + plan.timer
                sent.data, sent.at, sent.due = data, now, due
                out.append((plan.cob_id, data))
            if plan.timer > 0:
                next_sample = min(next_sample, _on_grid(sent.due))
        self._next_sample = next_sample if quiet else float("-inf")
        return out


def _on_grid(t: float) -> float:
    """The instant of the grid nearest to ``t`` (module docstring: GRID)."""
    return round(t / GRID) * GRID if math.isfinite(t) else t


class PdoTicker:
    """One thread per simulator: every ``tick`` seconds, each Operational drive sends
    what is due (:meth:`TransmitPdos.due`) on the virtual bus.

    The thread shares the interpreter with whatever runs in the same process (the
    serial link's thread, a bridge under test), so it wakes only when a drive
    wants a sample: every tick while one moves, else at the earliest quiet sample
    or event timer of all (``next_sample``). While no drive is Operational
    (``transmitting``) it sleeps until :meth:`wake`. A drive calls :meth:`wake`
    when it enters Operational or gets an SDO write (``TransmitPdos.touch``), so a
    change is still sampled at once.
    """

    def __init__(self, drives: Callable[[], Iterable[object]], clock: Callable[[], float], *,
                 tick: float = TICK) -> None:
        if not tick > 0:
            raise ValueError("the PDO tick must be positive")
        self._drives = drives
        self._clock = clock
        self.tick = tick
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._thread = threading.Thread(target=self._run, name="sim-tpdo", daemon=True)
        self._thread.start()

    def wake(self) -> None:
        """A drive entered Operational or was written: sample at the next tick."""
        self._wake.set()

    def _run(self) -> None:
        next_at = time.monotonic()
        while not self._stop.is_set():
            drives = [d for d in self._drives() if getattr(d, "transmitting", True)]
            if not drives:
                self._wake.wait(IDLE_WAIT)
                self._wake.clear()
                next_at = time.monotonic()
                continue
            now = self._clock()  # one instant for all: their next samples coincide
            for drive in drives:
                send = getattr(drive, "send_pdos", None)
                if send is not None:
                    try:
                        send(now)
                    except can.CanError:
                        return  # the bus is closed: the simulator is closing
            next_at += self.tick
            delay = next_at - time.monotonic()
            if delay < 0:  # late (a loaded machine): skip ahead, never burst
                next_at, delay = time.monotonic(), 0.0
            # Every drive quiet: sleep until the first wants a sample (bounded by
            # QUIET, whatever the simulator's clock does), or until wake().
            wanted = min((getattr(d, "next_sample", float("-inf")) for d in drives))
            quiet = min(wanted - self._clock(), QUIET)
            if quiet > delay:
                next_at, delay = next_at + quiet - delay, quiet
            if self._wake.wait(delay):
                # A tick after the wake, as a ticking drive would sample it: the
                # answer to the SDO write that woke it goes out first.
                self._wake.clear()
                self._stop.wait(self.tick)
                next_at = time.monotonic()

    def close(self) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread is not threading.current_thread():
            self._thread.join(5)


__all__ = ["ABORT_MAP_LENGTH", "ABORT_NOT_MAPPABLE", "ABORT_UNSUPPORTED", "PdoTicker",
           "TICK", "TransmitPdos", "install_mapping_rules", "mapped_variable", "mapping_subs"]
