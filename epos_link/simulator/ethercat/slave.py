"""One simulated EPOS4 as an EtherCAT slave: the PDI side of its ESC. Pure; time is passed in.

What the firmware behind the ESC does (guide chapter 4; ETG.1000.6):

* the EtherCAT state machine (guide 4.2, Tables 4-17..4-19): the master writes a
  state to AL control 0x0120 (bits 0..3; bit 4 acknowledges an error); the
  slave answers in AL status 0x0130 (bit 4: error indication) and AL status
  code 0x0134. Allowed: INIT->PRE-OP, PRE-OP->SAFE-OP, SAFE-OP->OP and every
  step down; anything else is refused with the error flag and a code
  (ETG.1000.6 Table 11): 0x0011 invalid requested state change, 0x0012 unknown
  state, 0x0013 bootstrap not supported, 0x0016 invalid mailbox configuration
  (SM0/SM1 not as the SII says), 0x001D/0x001E invalid output/input
  configuration (SM2/SM3 not matching the PDO assignment), 0x001B SM watchdog.
  **chosen**: while the error flag is set, a request to a higher state without
  the acknowledge bit is ignored; lower ones are carried out;
* the mailbox (PRE-OP, SAFE-OP, OP): a message the master wrote to SM0 is
  answered through SM1 (:mod:`.coe`); replies queue while SM1 is full;
  ``reply_delay(message)`` may hold a reply back for some seconds (a slow
  service, :mod:`.quirks` ``late``), while process data goes on;
  **chosen**: in INIT a message is dropped;
* process data: in SAFE-OP and OP the inputs (TxPDO, SM3) are sampled from the
  drive whenever the master reads them; only in OP are the outputs (RxPDO, SM2)
  written to the drive (guide Table 4-17: SAFE-OP "ignoring new setpoint
  values"). Outside OP the firmware deactivates SM2 through the PDI (ESC
  register 0x0807 bit 0; the Beckhoff Slave Stack Code's ``StopOutputHandler``
  on leaving OP), so the master's output write earns no working counter there:
  a master sees a slave that left OP by its short working counter, as SOEM's
  ``ecatcheck`` expects. An output object is written when its value differs from the last
  one written (the first cycle in OP writes all), except the controlword
  6040h, which is given to the drive with every frame: CiA 402-2 6.4.1 defines
  the device control commands by the controlword's value, so a drive that
  stopped by itself (quick stop, 6007h reaction) and still receives "enable
  operation" takes transition 16 back up when 605Ah allows it, as issue 31
  saw on an independent slave (**chosen**: the strict reading). A value the
  dictionary refuses (e.g. modes of operation 0) is skipped.
  ``apply_outputs`` may replace the writing of one frame's objects (the drive
  application does it under its lock and records what happened);
* the process-data watchdog (ESC registers 0x0400 divider, default 2498 =
  100 us, and 0x0420 time, default 1000 = 100 ms; enabled by SM2 control bit 6,
  which the SII sets): in OP, when no write to SM2 came for that long, the
  slave drops to SAFE-OP with code 0x001B, clears 0x0440 bit 0, and calls
  ``on_leave_op("watchdog")`` (the drive's reaction: :mod:`.drive_app`).
  Any other way out of OP calls ``on_leave_op("state change")``.
"""
from __future__ import annotations

from enum import IntEnum
from typing import Callable, Optional

from . import esc as regs
from .coe import MBX_COE, ObjectAccess, SdoServer, mailbox_message, parse_mailbox
from .esc import Esc
from .frame import Command, Datagram
from .pdo import EthercatObjects, PdoLayout, read_layout
from .sii import SYNC_MANAGERS, build_sii

__all__ = ["AlState", "AlStatusCode", "EthercatSlave"]


class AlState(IntEnum):
    INIT = 1
    PRE_OP = 2
    BOOT = 3
    SAFE_OP = 4
    OP = 8


class AlStatusCode(IntEnum):
    """ETG.1000.6 Table 11 (the ones this slave raises)."""

    NONE = 0x0000
    INVALID_STATE_CHANGE = 0x0011
    UNKNOWN_STATE = 0x0012
    BOOTSTRAP_NOT_SUPPORTED = 0x0013
    INVALID_MAILBOX_CONFIG = 0x0016
    SM_WATCHDOG = 0x001B
    INVALID_OUTPUT_CONFIG = 0x001D
    INVALID_INPUT_CONFIG = 0x001E


# Objects given to the drive with every frame, not only when they change (docstring).
LEVEL_OBJECTS = frozenset({(0x6040, 0)})
_UP = {(AlState.INIT, AlState.PRE_OP), (AlState.PRE_OP, AlState.SAFE_OP), (AlState.SAFE_OP, AlState.OP)}
_READS = {Command.APRD, Command.FPRD, Command.BRD}
_WRITES = {Command.APWR, Command.FPWR, Command.BWR}
_READ_WRITES = {Command.APRW, Command.FPRW, Command.BRW}
_AUTO_INCREMENT = {Command.APRD, Command.APWR, Command.APRW, Command.ARMW}
_CONFIGURED = {Command.FPRD, Command.FPWR, Command.FPRW, Command.FRMW}
_BROADCAST = {Command.BRD, Command.BWR, Command.BRW}
_LOGICAL: dict[int, tuple[bool, bool]] = {Command.LRD: (True, False), Command.LWR: (False, True), Command.LRW: (True, True)}


class EthercatSlave:
    """An ESC plus the EPOS4 firmware's EtherCAT side, over the drive's objects."""

    def __init__(self, objects: ObjectAccess, serial: int = 1, *,
                 on_enter_op: Callable[[], None] = lambda: None,
                 on_leave_op: Callable[[str], None] = lambda cause: None,
                 complete_access: bool = True, ca_padding: bool = True,
                 reply_delay: Callable[[bytes], float] = lambda message: 0.0,
                 apply_outputs: Optional[Callable[[list[tuple[int, int, bytes]]], None]] = None
                 ) -> None:
        self.objects = EthercatObjects(objects, lambda: self.state is AlState.PRE_OP)
        self.esc = Esc(build_sii(serial, ca=complete_access))
        self.on_enter_op = on_enter_op
        self.on_leave_op = on_leave_op
        self.ca_padding = ca_padding
        self.reply_delay = reply_delay
        self.apply_outputs = apply_outputs if apply_outputs is not None else self._write_outputs
        self.state = AlState.INIT
        self.layout: Optional[PdoLayout] = None
        self.sdo = SdoServer(self.objects, SYNC_MANAGERS[1].length, ca_padding=ca_padding)
        self._replies: list[tuple[float, int, bytes]] = []  # due time, type, data
        self._counter = 0
        self._written: dict[tuple[int, int], bytes] = {}
        self.now = 0.0
        self._triggered = 0.0  # last SM2 write (process data watchdog)
        self.esc.sm_deactivated[2] = True  # outputs only in OP (docstring)
        self.esc.on_write = self._on_write
        self.esc.on_sm_filled = self._on_sm_filled
        self.esc.on_sm_emptied = self._on_sm_emptied
        self.esc.before_sm_read = self._before_sm_read

    # -- datagrams ---------------------------------------------------------------------------

    def process(self, dg: Datagram, now: float) -> None:
        """Act on one datagram passing this slave (ETG.1000.4 5.4): data and working counter."""
        self.now = now
        command = dg.command
        if command in _LOGICAL:
            read, write = _LOGICAL[command]
            dg.wkc += self.esc.logical(dg.address, dg.data, read, write)
            return
        if command in _AUTO_INCREMENT or command in _BROADCAST:
            addressed = command in _BROADCAST or dg.adp == 0
            dg.address = (dg.address & 0xFFFF0000) | ((dg.adp + 1) & 0xFFFF)  # each slave counts
        elif command in _CONFIGURED:
            addressed = dg.adp == self.esc.u16(regs.STATION_ADDRESS)
        else:
            return  # NOP or unknown: passed on untouched
        if not addressed and command not in (Command.ARMW, Command.FRMW):
            return
        ado, size = dg.ado, len(dg.data)
        if command in (Command.ARMW, Command.FRMW):
            if addressed:
                command = Command.APRD
            elif self.esc.write(ado, bytes(dg.data)):
                dg.wkc += 1
                return
            else:
                return
        if command in _READS:
            got = self.esc.read(ado, size)
            if got is not None:
                dg.data[:] = bytes(a | b for a, b in zip(dg.data, got)) if command is Command.BRD else got
                dg.wkc += 1
        elif command in _WRITES:
            if self.esc.write(ado, bytes(dg.data)):
                dg.wkc += 1
        elif command in _READ_WRITES:
            got = self.esc.read(ado, size)
            wrote = self.esc.write(ado, bytes(dg.data))
            if got is not None:
                dg.data[:] = got
            dg.wkc += (1 if got is not None else 0) + (2 if wrote else 0)

    # -- time --------------------------------------------------------------------------------

    def watchdog_time(self) -> Optional[float]:
        """The process-data watchdog in seconds, or None when it is off."""
        _start, _length, control, enabled = self.esc.sm(2)
        count = self.esc.u16(regs.PD_WATCHDOG)
        if not enabled or not control & 0x40 or not count:
            return None
        return (self.esc.u16(regs.WATCHDOG_DIVIDER) + 2) / 25e6 * count

    def tick(self, now: float) -> None:
        """Expire the process-data watchdog if it is due; deliver a held reply."""
        self.now = now
        self._deliver()
        timeout = self.watchdog_time()
        if self.state is not AlState.OP or timeout is None:
            return
        if now - self._triggered > timeout:
            self.esc.memory[regs.PD_WATCHDOG_STATUS] &= 0xFE
            self._enter(AlState.SAFE_OP)
            self._fail(AlStatusCode.SM_WATCHDOG)
            self.on_leave_op("watchdog")

    # -- the state machine -----------------------------------------------------------------

    def _on_write(self, first: int, last: int) -> None:
        if first <= regs.AL_CONTROL <= last:
            self._al_control(self.esc.u16(regs.AL_CONTROL))

    def _status(self) -> int:
        return self.esc.u16(regs.AL_STATUS)

    def _fail(self, code: AlStatusCode) -> None:
        self.esc.set_u16(regs.AL_STATUS, self.state | 0x10)
        self.esc.set_u16(regs.AL_STATUS_CODE, code)

    def _al_control(self, control: int) -> None:
        requested, ack = control & 0x0F, bool(control & 0x10)
        error = bool(self._status() & 0x10)
        if error and ack:
            self.esc.set_u16(regs.AL_STATUS, self.state)
            self.esc.set_u16(regs.AL_STATUS_CODE, 0)
            error = False
        if requested not in AlState._value2member_map_:
            if not error:
                self._fail(AlStatusCode.UNKNOWN_STATE)
            return
        target = AlState(requested)
        if target is self.state:
            return
        if error and target > self.state:
            return
        if target is AlState.BOOT:
            self._fail(AlStatusCode.BOOTSTRAP_NOT_SUPPORTED)
            return
        if target > self.state and (self.state, target) not in _UP:
            self._fail(AlStatusCode.INVALID_STATE_CHANGE)
            return
        code = self._check(target) if target > self.state else AlStatusCode.NONE
        if code is not AlStatusCode.NONE:
            self._fail(code)
            return
        left_op = self.state is AlState.OP
        self._enter(target, keep_error=error)
        if left_op:
            self.on_leave_op("state change")

    def _check(self, target: AlState) -> AlStatusCode:
        if target is AlState.PRE_OP:
            for n in (0, 1):
                start, length, control, enabled = self.esc.sm(n)
                want = SYNC_MANAGERS[n]
                if not enabled or (start, length, control & 0x0F) != (want.start, want.length,
                                                                      want.control & 0x0F):
                    return AlStatusCode.INVALID_MAILBOX_CONFIG
        elif target is AlState.SAFE_OP:
            try:
                layout = read_layout(self.objects)
            except Exception:  # an unreadable or unmappable assignment
                return AlStatusCode.INVALID_OUTPUT_CONFIG
            for n, size, code in ((2, layout.output_size, AlStatusCode.INVALID_OUTPUT_CONFIG),
                                  (3, layout.input_size, AlStatusCode.INVALID_INPUT_CONFIG)):
                start, length, control, enabled = self.esc.sm(n)
                if size and (not enabled or start != SYNC_MANAGERS[n].start or length != size
                             or control & 0x0F != SYNC_MANAGERS[n].control & 0x0F):
                    return code
            self.layout = layout
        return AlStatusCode.NONE

    def _enter(self, target: AlState, keep_error: bool = False) -> None:
        self.state = target
        self.esc.sm_deactivated[2] = target is not AlState.OP
        self.esc.set_u16(regs.AL_STATUS, target | (0x10 if keep_error else 0))
        if target is AlState.INIT:
            self._replies.clear()
            self.sdo = SdoServer(self.objects, SYNC_MANAGERS[1].length,
                                 ca_padding=self.ca_padding)
        if target <= AlState.PRE_OP:
            self.layout = None
        if target is AlState.OP:
            self._written.clear()
            self._triggered = self.now
            self.esc.memory[regs.PD_WATCHDOG_STATUS] |= 0x01
            self.on_enter_op()

    # -- SyncManager events ------------------------------------------------------------------

    def _on_sm_filled(self, n: int) -> None:
        if n == 0:
            data = bytes(self.esc.sm_area(0))
            self.esc.empty_mailbox(0)
            if self.state is AlState.INIT:
                return
            try:
                header, body = parse_mailbox(data)
            except ValueError:
                return  # **chosen**: a malformed mailbox header is dropped
            delay = self.reply_delay(body) if header.kind == MBX_COE else 0.0
            kind, reply = self.sdo.handle(header.kind, body)
            self._replies.append((self.now + delay, kind, reply))
            self._deliver()
        elif n == 2:
            self._triggered = self.now
            self.esc.memory[regs.PD_WATCHDOG_STATUS] |= 0x01
            if self.state is AlState.OP and self.layout is not None:
                self._apply_outputs(bytes(self.esc.sm_area(2)))

    def _on_sm_emptied(self, n: int) -> None:
        if n == 1:
            self._deliver()

    def _deliver(self) -> None:
        if self._replies and not self.esc.mailbox_full[1] and self._replies[0][0] <= self.now:
            _due, kind, data = self._replies.pop(0)
            self._counter = self._counter % 7 + 1  # 1..7; 0 is reserved (ETG.1000.6 5.6.1)
            self.esc.fill_sm(1, mailbox_message(kind, self._counter, data))

    def _before_sm_read(self, n: int) -> None:
        if n == 3 and self.layout is not None and self.state in (AlState.SAFE_OP, AlState.OP):
            start = self.esc.sm(3)[0]
            try:
                inputs = self.layout.pack_inputs(self.objects)
            except Exception:  # **chosen**: a failed sample keeps the last inputs
                return
            self.esc.memory[start:start + len(inputs)] = inputs

    def _apply_outputs(self, data: bytes) -> None:
        assert self.layout is not None
        changed = []
        for entry, value in self.layout.split_outputs(data):
            key = (entry.index, entry.subindex)
            if self._written.get(key) == value and key not in LEVEL_OBJECTS:
                continue
            self._written[key] = value
            changed.append((entry.index, entry.subindex, value))
        if changed:
            self.apply_outputs(changed)

    def _write_outputs(self, changed: list[tuple[int, int, bytes]]) -> None:
        for index, subindex, value in changed:
            try:
                self.objects.write(index, subindex, value)
            except Exception:  # refused by the dictionary: skipped (see the docstring)
                pass
