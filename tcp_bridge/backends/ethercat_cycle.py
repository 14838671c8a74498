"""The process-data cycle of an ``ethercat`` bus, and the recovery of slaves that drop out.

Rules:

1. **Two locks, and the process data never waits for the mailbox.** The
   process data, the slaves' states and the images (a cycle's send/receive, a
   state read or change, a write into the output image) hold
   :attr:`CycleLoop.lock`, each for one bounded exchange. A CoE transfer (SDO
   upload/download, of any length: an EPOS4 takes seconds to store its
   parameters, 1010h) holds :attr:`CycleLoop.mailbox` instead, never the cycle's
   lock, and releases the GIL while SOEM waits (pysoem ``release_gil=True``), so
   the cycle runs on meanwhile. SOEM is made for that: each frame has its own
   index, and a thread that receives another thread's frame files it in that
   index's buffer (SOEM ``nicdrv.c`` ``ecx_getindex``/``ecx_inframe``, with their
   mutexes), which is how SOEM's own ``simple_test`` runs ``ecatcheck`` beside
   the cycle. The mailbox lock keeps one CoE transfer at a time (SOEM counts
   mailbox sessions per slave) and the recovery's ``reconfig``/``recover``
   (mailbox traffic of their own) out of a transfer: the cycle never waits for
   it, a recovery step finding it busy is tried at the next check. The cycle
   lock serves the cycle first (:class:`~tcp_bridge.backends.cycle_lock.CycleLock`):
   a burst of image writes delays a cycle by one write, not by the burst.
2. **The cycle** (:meth:`CycleLoop.step`, every ``cycle_ms`` on its own thread):
   cycle hooks run (a CSP set-point generator writes its next target), the output
   images are copied into the I/O map, ``send_processdata`` /
   ``receive_processdata`` (GIL released), the input images are copied out,
   the working counter is compared with ``expected_wkc``, and then the *input
   hooks* run on the inputs of this very cycle (:mod:`.ethercat_hold`: the
   outputs that follow the drive), before a state check and before the next
   send. Deadlines are absolute (the next cycle is due one period after the
   last one was due), so jitter does not accumulate; a cycle that starts more
   than a period late is an *overrun* and the schedule restarts from now rather
   than bursting to catch up.
3. **Drop-out** (as SOEM's ``simple_test`` ``ecatcheck``): a short working
   counter, or a slave seen out of OP, makes the loop read every slave's state
   (AL status register, ETG.1000.6 6.4.1). A slave not in OP is *lost*: its
   node answers every transfer at once with the AL status code and its text
   (a silent node, as on CAN, :mod:`tcp_bridge.bus.health`), and ``on_lost``
   tells the backend (its outputs follow the drive from then on, its cyclic
   run ends). The recovery, on the cycle thread between cycles, one step per
   check: a state with the error flag (SAFEOP+ERROR, and PREOP+ERROR or
   INIT+ERROR too) is acknowledged first, in the state it shows, since a slave
   refuses every higher state until its error indication is acknowledged
   (ETG.1000.6 6.4.1, AL Control's Acknowledge bit; SOEM's ``simple_test`` acks
   SAFEOP+ERROR only, and a slave back in INIT+ERROR was ``reconfig()``-ured for
   ever: INIT went through, PREOP was refused); a slave in SAFEOP is asked for OP only
   at the second check in a row that finds it there, so that the inputs of
   the cycle just before came from the slave in SAFE-OP (the EPOS4 sends
   actual values in SAFE-OP: guide Table 4-17) and the outputs that follow its
   drive were made from them; a slave still present in a lower state is
   ``reconfig()``-ured, one that vanished is ``recover()``-ed when it is back.
   A slave whose state reads get no answer (NONE) is lost only when they have
   failed :data:`SILENT_CHECKS` times in a row *and* for ``silent_after`` seconds
   (the backend's ``watchdog_ms``): until its process-data watchdog has run out a
   slave whose frames are late has not left OP by its own rule (ETG.1000.4, SM
   watchdog), so a loaded host's late answers are not a drop-out (a suite at load
   4 lost a simulated slave after three 16 ms checks), and a slave that did leave
   OP says so in its state when it answers again.
   A state read that gets no answer (NONE) makes a slave lost only at the
   :data:`SILENT_CHECKS`-th in a row: on a loaded host a frame comes back late
   now and then, and a slave wrongly called lost would have its outputs follow
   its drive and its cyclic run ended.
4. **The link**: when no frame came back for ``link_cycles`` cycles in a row
   (``receive_processdata`` < 1: the cable, the card, every slave's power), the
   bus's device is silent (:attr:`CycleLoop.link_down`).
5. **The interpreter's switch interval.** CPython hands the GIL to a waiting
   thread only after the running one held it for ``sys.getswitchinterval()``
   (5 ms by default), so a cycle thread woken on time could wait that long
   behind a thread running Python code (a client's request, an SDO transfer's
   bookkeeping): ``bench/ethercat.py`` measured a 5.5 ms max jitter from it.
   While any cycle runs, the interval is a quarter of the shortest cycle (never
   longer than it was), and it is put back when the last cycle stops.
"""
from __future__ import annotations

import logging
import sys
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable, Dict, List, Optional, Tuple

from .cycle_lock import CycleLock

log = logging.getLogger("tcp_bridge.backends.ethercat")
# The counts at close, which docs/hardware.md ("Cycle time and jitter") promises: the
# bridge shows this logger's INFO lines without -v (tcp_bridge.cli.ALWAYS_INFO).
summary_log = logging.getLogger("tcp_bridge.summary")

# pysoem state constants (SOEM ethercattype.h ec_state), repeated so the module
# and its tests do not need pysoem itself.
NONE, INIT, PREOP, BOOT, SAFEOP, OP = 0x00, 0x01, 0x02, 0x03, 0x04, 0x08
ERROR = ACK = 0x10
STATE_MASK = 0x0F  # the AL status's state, without the error flag
STATE_NAMES = {NONE: "NONE", INIT: "INIT", PREOP: "PREOP", BOOT: "BOOT", SAFEOP: "SAFEOP",
               OP: "OP"}
RECOVER_TIMEOUT_US = 2000  # SOEM EC_TIMEOUTRET: one exchange's wait
SILENT_CHECKS = 3  # state reads in a row without an answer before a slave is lost (rule 3)
LOCK_WAIT_LIMIT = 1.0  # s: the longest a transfer waits for a due cycle (cycle_lock)


class _SwitchInterval:
    """Rule 5: the interpreter's switch interval while cycles run (process-wide)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._loops: Dict[int, float] = {}  # id(loop) -> its period
        self._before: Optional[float] = None

    def enter(self, loop: "CycleLoop") -> None:
        with self._lock:
            if not self._loops:
                self._before = sys.getswitchinterval()
            self._loops[id(loop)] = loop.period
            self._apply()

    def leave(self, loop: "CycleLoop") -> None:
        with self._lock:
            if self._loops.pop(id(loop), None) is None:
                return
            if self._loops:
                self._apply()
            elif self._before is not None:
                sys.setswitchinterval(self._before)
                self._before = None

    def _apply(self) -> None:
        assert self._before is not None
        wanted = min(self._before, max(min(self._loops.values()) / 4.0, 1e-4))
        sys.setswitchinterval(wanted)


_SWITCH = _SwitchInterval()


def state_name(state: int) -> str:
    base = STATE_NAMES.get(state & STATE_MASK, f"0x{state & STATE_MASK:02X}")
    return base + ("+ERROR" if state & ERROR else "")


@dataclass
class CycleStats:
    """What the cycle measured (docs/hardware.md, "EtherCAT"): counts since opening."""

    cycles: int = 0
    wkc_errors: int = 0  # cycles with a working counter below expected_wkc
    no_frame: int = 0  # cycles with no frame back at all
    overruns: int = 0  # cycles started more than a period late
    max_late_ms: float = 0.0  # the latest start of a cycle after its deadline


Hook = Callable[[int], None]


class CycleLoop:
    """The process data of one master; ``slaves`` are pysoem slaves by position (1-based)."""

    def __init__(self, master: Any, slaves: Dict[int, Any], period: float, *,
                 al_text: Callable[[int], str], link_cycles: int = 25,
                 silent_after: float = 0.1,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.master = master
        self.slaves = slaves
        self.period = period
        self.lock = CycleLock(wait_limit=LOCK_WAIT_LIMIT)  # rule 1
        self.fresh = threading.Condition(threading.Lock())  # notified after each cycle
        self.stats = CycleStats()
        self.outputs: Dict[int, bytearray] = {p: bytearray(bytes(s.output)) for p, s in slaves.items()}
        self.inputs: Dict[int, bytes] = {p: bytes(s.input) for p, s in slaves.items()}
        self.lost: Dict[int, str] = {}  # position -> why (AL status), rule 3
        self.link_cycles = link_cycles
        self.link_down = False
        self._dark = 0  # cycles in a row without a frame
        self._check = False
        # False while the backend brings the slaves to OP: a short working counter is
        # expected then, and not a drop-out (set by the backend when opening ends).
        self.supervise = False
        self._hooks: List[Hook] = []
        self.input_hooks: List[Hook] = []  # rule 2: on the inputs of this cycle
        self.on_lost: Callable[[int, str], None] = lambda position, why: None
        self.mailbox = threading.Lock()  # rule 1: one CoE transfer at a time
        self._armed: Dict[int, int] = {}  # position -> the check that found it in SAFEOP
        self._checks = 0
        self._frame_back = False  # the last cycle's frame came back
        # position -> (state reads in a row without answer, when the first of them was)
        self._silent: Dict[int, Tuple[int, float]] = {}
        self.silent_after = silent_after  # rule 3: a silent slave is lost no sooner
        self._al_text = al_text
        self._clock = clock
        self._stop = threading.Event()
        self._thread: Optional[threading.Thread] = None

    # -- the API for cyclic set-points (tcp_bridge.backends.ethercat, "CSP") ----------

    def add_hook(self, hook: Hook) -> None:
        """Call ``hook(cycle)`` at the start of every cycle, on the cycle thread, before
        the outputs are sent. It must be quick; one that raises is removed and logged."""
        with self.lock:
            self._hooks.append(hook)

    def remove_hook(self, hook: Hook) -> None:
        with self.lock:
            if hook in self._hooks:
                self._hooks.remove(hook)

    # -- the cycle --------------------------------------------------------------------

    def start(self) -> None:
        _SWITCH.enter(self)
        self._thread = threading.Thread(target=self._run, name="ethercat-cycle", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            _SWITCH.leave(self)
            s = self.stats
            summary_log.info("ethercat: %d cycles, %d with a short working counter, %d "
                             "without a frame, %d overruns, latest start %.2f ms after its "
                             "deadline", s.cycles, s.wkc_errors, s.no_frame, s.overruns,
                             s.max_late_ms)

    def _run(self) -> None:
        due = self._clock()
        while not self._stop.is_set():
            late = self._clock() - due
            if late > self.period:
                self.stats.overruns += 1
                due = self._clock()
            if late > self.period / 2 and self.stats.max_late_ms <= self.period * 500.0:
                log.warning("ethercat: a cycle started %.1f ms late (cycle %.1f ms): the host "
                            "is loaded, or cycle_ms is too short for it", late * 1000.0,
                            self.period * 1000.0)
            self.stats.max_late_ms = max(self.stats.max_late_ms, late * 1000.0)
            try:
                self.step()
            except Exception:  # a bug must not end the cycle: the watchdogs would trip
                log.exception("ethercat cycle failed")
            due += self.period
            self._stop.wait(max(0.0, due - self._clock()))

    def step(self) -> int:
        """One cycle (rule 2), then a state check when needed (rule 3); the working counter."""
        with self.lock.priority():
            count = self.stats.cycles
            for hook in list(self._hooks):
                try:
                    hook(count)
                except Exception:
                    log.exception("ethercat cycle hook %r failed: removed", hook)
                    self._hooks.remove(hook)
            for position, slave in self.slaves.items():
                slave.output = bytes(self.outputs[position])
            self.master.send_processdata(release_gil=True)
            wkc = int(self.master.receive_processdata(2000, release_gil=True))
            for position, slave in self.slaves.items():
                self.inputs[position] = bytes(slave.input)
            self._account(wkc)
            self._frame_back = wkc > 0
            if wkc > 0:
                for hook in list(self.input_hooks):
                    try:
                        hook(count)
                    except Exception:
                        log.exception("ethercat input hook %r failed: removed", hook)
                        self.input_hooks.remove(hook)
            if self.supervise and (self._check or wkc < int(self.master.expected_wkc)):
                self._check_states()
        with self.fresh:
            self.stats.cycles += 1
            self.fresh.notify_all()
        return wkc

    def _account(self, wkc: int) -> None:
        if wkc < 1:
            self.stats.no_frame += 1
            self._dark += 1
            if self._dark >= self.link_cycles and not self.link_down:
                self.link_down = True
                log.warning("ethercat: no frame came back for %d cycles: the link is down",
                            self._dark)
        else:
            if self.link_down:
                log.warning("ethercat: frames come back again")
            self._dark, self.link_down = 0, False
        if wkc < int(self.master.expected_wkc):
            self.stats.wkc_errors += 1

    def wait_cycles(self, count: int, timeout: float) -> bool:
        """Wait until ``count`` more cycles have completed; False after ``timeout`` s."""
        with self.fresh:
            target = self.stats.cycles + count
            return self.fresh.wait_for(lambda: self.stats.cycles >= target, timeout)

    # -- drop-out and recovery (rule 3) -----------------------------------------------

    def _check_states(self) -> None:
        self.master.read_state()
        self._check = False
        self._checks += 1
        for position, slave in self.slaves.items():
            state = int(slave.state)
            if state == OP:
                self._armed.pop(position, None)
                self._silent.pop(position, None)
                if position in self.lost:
                    log.warning("ethercat: slave %d is back in OP", position)
                    del self.lost[position]  # after the log: a reader of lost sees both
                continue
            self._check = True  # look again next cycle until every slave is in OP
            if state == NONE and position not in self.lost:
                # No answer to the state read (frames lost on a loaded host) is not yet a
                # drop-out: SILENT_CHECKS checks in a row must find it silent.
                count, since = self._silent.get(position, (0, self._clock()))
                self._silent[position] = (count + 1, since)
                if count + 1 < SILENT_CHECKS or self._clock() - since < self.silent_after:
                    continue
            self._silent.pop(position, None)
            if position not in self.lost:
                self.lost[position] = self.describe(position, state)
                log.warning("ethercat: slave %d dropped out: %s", position, self.lost[position])
                self.on_lost(position, self.lost[position])
            self._recover(position, slave, state)

    def describe(self, position: int, state: Optional[int] = None) -> str:
        slave = self.slaves[position]
        state = int(slave.state) if state is None else state
        code = int(getattr(slave, "al_status", 0) or 0)
        why = f"slave {position} is in {state_name(state)}"
        if code:
            why += f", AL status 0x{code:04X} {self._al_text(code)}"
        return why

    def _recover(self, position: int, slave: Any, state: int) -> None:
        if state != SAFEOP:
            self._armed.pop(position, None)
        shown = state & STATE_MASK
        if state & ERROR and shown != NONE and shown in STATE_NAMES:  # acknowledged first,
            # in the state it shows (rule 3); a garbled read (no such state) is not echoed
            slave.state = shown | ACK
            slave.write_state()
        elif state == SAFEOP:
            # Rule 3: OP only at the second check in a row in SAFEOP, so that the inputs
            # the input hooks just used came from the slave in SAFE-OP.
            if self._armed.get(position) == self._checks - 1 and self._frame_back:
                slave.state = OP
                slave.write_state()
            else:
                self._armed[position] = self._checks
        elif not self.mailbox.acquire(blocking=False):
            return  # a CoE transfer is running (rule 1): the next check tries again
        else:
            try:
                if state > NONE:
                    if slave.reconfig(RECOVER_TIMEOUT_US) >= SAFEOP:  # SAFEOP: OP later
                        self._check = True
                elif slave.recover(RECOVER_TIMEOUT_US) > 0:  # a slave that vanished is back
                    self._check = True
            finally:
                self.mailbox.release()
