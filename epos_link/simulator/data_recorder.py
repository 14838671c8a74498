"""The simulated EPOS4's own data recorder, 31E0h-31E9h, modelled from maxon's XDD.

The facts (objects, types, ranges, the period's 10 us unit, the 16 trigger modes,
the control and status values, the int32 buffers) are :mod:`epos_link.data_recorder`,
whose docstring cites them; this module adds the objects to a simulated drive's
dictionary (:func:`add_recorder_objects`, called by
:func:`~epos_link.simulator.od.load_object_dictionary`) and samples the drive.

**Time.** The recorder samples in the drive's own time, exactly every period: when
the drive model catches up with the clock (:meth:`Drive.update
<epos_link.simulator.drive.Drive.update>`), it first steps to each sampling instant
that falls in the interval and takes the sample there (:meth:`DataRecorder.sample_times`,
:meth:`DataRecorder.take`). So a 1 ms recording has its samples 1 ms apart in the
drive's time, however late the host's threads run, and its positions are the
profile's at those instants, as a real drive's recorder samples in its control cycle.

**Behaviour**, with what is **chosen** where the sources are silent (the same
choices as the client's, :mod:`epos_link.tools.record_on_drive`):

* 31E4h:01 = 1 (start) or 3 (start, trigger forced) clears the buffers and arms:
  statusword (31E4h:02) bit 0 "running" set, bit 1 "triggered" clear. The first
  sample is taken at the start. 0 stops (bit 0 clears; what was recorded stays
  readable). Any other value: 06090030h (chosen).
* The trigger is evaluated on each sample of the trigger variable (31E2h:01,
  masked by :05) with its mode (:02) and high and low values (:03, :04),
  :func:`epos_link.data_recorder.triggered`, but only once the preceding samples
  (:06) are in the buffer (chosen, so the trigger sample is always at index
  "preceding": the buffer says nothing else of where it is). A forced start fires
  at the first such sample.
* After the trigger the recorder fills the buffer up to 31E1h:02 samples
  (preceding ones included), then stops: bit 0 clears, bit 1 stays.
* 31E5h:01 the samples in the buffer; 31E6h-31E9h:01 each channel's samples as
  little-endian int32, oldest first (chosen: the XDD gives 2000 bytes, not the
  order); :02 "part 1" the same bytes (chosen: the XDD gives no other meaning).
  A channel whose variable is 0 reads empty. 31E5h:02 (buffer timestamp) and :03
  (snapshot) are not modelled: 0 and 20 zero bytes (their meaning is unknown).
* A variable (31E0h, 31E2h:01) must be ``(index << 16) | (subindex << 8)`` of an
  integer object of up to 32 bits in the dictionary, or 0 (channel unused),
  else 06090030h (chosen). The configuration (31E0h-31E2h) cannot change while
  the recorder runs: 08000022h "data cannot be transferred or stored because of
  the present device state" (chosen, CiA 301 Table 22).
"""
from __future__ import annotations

import math
from collections import deque
from functools import partial
from typing import TYPE_CHECKING, Any, Callable, Iterator, Optional

from canopen import SdoAbortedError
from canopen.objectdictionary import ObjectDictionary, ODRecord, ODVariable, datatypes

from .. import data_recorder as facts
from ..data_recorder import Control, RecorderStatus, TriggerMode

if TYPE_CHECKING:
    from .od import ObjectStore, Value

__all__ = ["DataRecorder", "add_recorder_objects"]

ABORT_RANGE = 0x06090030
ABORT_STATE = 0x08000022  # CiA 301 Table 22: present device state
_INTEGER_TYPES = {datatypes.INTEGER8, datatypes.INTEGER16, datatypes.INTEGER32,
                  datatypes.UNSIGNED8, datatypes.UNSIGNED16, datatypes.UNSIGNED32,
                  datatypes.BOOLEAN}


def _var(index: int, sub: int, name: str, data_type: int, access: str, default: Any = 0,
         low: Optional[int] = None, high: Optional[int] = None) -> ODVariable:
    var = ODVariable(name, index, sub)
    var.data_type = data_type
    var.access_type = access
    var.default = default
    var.min, var.max = low, high
    return var


def _record(od: ObjectDictionary, index: int, name: str, members: list[ODVariable]) -> None:
    record = ODRecord(name, index)
    record.add_member(_var(index, 0, "Highest sub-index supported", datatypes.UNSIGNED8, "ro",
                           len(members)))
    for member in members:
        record.add_member(member)
    od.add_object(record)


def add_recorder_objects(od: ObjectDictionary) -> None:
    """31E0h-31E9h as the XDD has them (epos_link.data_recorder's table)."""
    u8, u16, u32, octets = (datatypes.UNSIGNED8, datatypes.UNSIGNED16, datatypes.UNSIGNED32,
                            datatypes.OCTET_STRING)
    prefix = "Internal data recorder"
    _record(od, facts.VARIABLE_INDEX, f"{prefix} variable index", [
        _var(facts.VARIABLE_INDEX, k, f"{prefix} variable index {k}", u32, "rw")
        for k in range(1, facts.CHANNELS + 1)])
    _record(od, facts.CONFIGURATION, f"{prefix} configuration", [
        _var(facts.CONFIGURATION, facts.PERIOD_SUB, f"{prefix} sampling period", u16, "rw", 120,
             facts.PERIOD_MIN, facts.PERIOD_MAX),
        _var(facts.CONFIGURATION, facts.MAX_SAMPLES_SUB, f"{prefix} max number of samples", u16,
             "rw", facts.MAX_SAMPLES, 1, facts.MAX_SAMPLES)])
    _record(od, facts.TRIGGER, f"{prefix} trigger", [
        _var(facts.TRIGGER, facts.TRIGGER_VARIABLE, f"{prefix} trigger variable index", u32, "rw"),
        _var(facts.TRIGGER, facts.TRIGGER_MODE, f"{prefix} trigger mode", u8, "rw", 0,
             0, max(TriggerMode)),
        _var(facts.TRIGGER, facts.TRIGGER_HIGH, f"{prefix} trigger high value", u32, "rw"),
        _var(facts.TRIGGER, facts.TRIGGER_LOW, f"{prefix} trigger low value", u32, "rw"),
        _var(facts.TRIGGER, facts.TRIGGER_MASK, f"{prefix} trigger mask", u32, "rw", 0xFFFFFFFF),
        _var(facts.TRIGGER, facts.PRECEDING, f"{prefix} trigger number of preceding samples",
             u16, "rw", 0, 0, facts.PRECEDING_MAX)])
    _record(od, facts.CONTROL, f"{prefix} control", [
        _var(facts.CONTROL, facts.CONTROLWORD_SUB, f"{prefix} controlword", u16, "rw"),
        _var(facts.CONTROL, facts.STATUSWORD_SUB, f"{prefix} statusword", u16, "ro")])
    _record(od, facts.DATA, f"{prefix} data", [
        _var(facts.DATA, facts.RECORDED_SUB, f"{prefix} number of recorded samples", u16, "ro"),
        _var(facts.DATA, facts.TIMESTAMP_SUB, "Internal recorder buffer timestamp", u32, "ro"),
        _var(facts.DATA, facts.SNAPSHOT_SUB, f"{prefix} snapshot", octets, "ro",
             bytes(facts.SNAPSHOT_SIZE))])
    for k, index in enumerate(facts.BUFFERS, start=1):
        _record(od, index, f"{prefix} buffer variable {k}", [
            _var(index, facts.COMPLETE_SUB, f"{prefix} buffer variable {k} complete", octets,
                 "ro", b""),
            _var(index, facts.PART1_SUB, f"{prefix} buffer variable {k} part 1", octets, "ro",
                 b"")])


class DataRecorder:
    """The recorder of one simulated drive, on its store (module docstring)."""

    def __init__(self, store: "ObjectStore", now: Callable[[], float]) -> None:
        self.store = store
        self.now = now  # the drive's time (Drive._now)
        self.status = RecorderStatus(0)
        self._channels: list[Optional[tuple[int, int]]] = []
        self._trigger_var: Optional[tuple[int, int]] = None
        self._period = 0.0
        self._size = facts.MAX_SAMPLES
        self._preceding = 0
        self._forced = False
        self._mode = TriggerMode.IS_VALUE
        self._high = self._low = 0
        self._mask = 0xFFFFFFFF
        self._t0 = 0.0
        self._taken = 0  # samples taken since the start
        self._previous: Optional[int] = None  # the trigger variable at the last sample
        self._before: deque[tuple[int, ...]] = deque(maxlen=1)
        self._after: list[tuple[int, ...]] = []
        s = store
        if facts.CONTROL not in s.od:
            return  # a dictionary without the recorder (an EDS given by a test)
        s.add_write_hook(facts.CONTROL, facts.CONTROLWORD_SUB, self._on_control)
        s.add_read_hook(facts.CONTROL, facts.STATUSWORD_SUB, lambda: int(self.status))
        s.add_read_hook(facts.DATA, facts.RECORDED_SUB, lambda: len(self.samples))
        for channel, index in enumerate(facts.BUFFERS):
            for sub in (facts.COMPLETE_SUB, facts.PART1_SUB):
                s.add_read_hook(index, sub, partial(self.buffer, channel))
        for sub in range(1, facts.CHANNELS + 1):
            s.add_write_hook(facts.VARIABLE_INDEX, sub, self._on_variable)
        for index, sub in ((facts.CONFIGURATION, facts.PERIOD_SUB),
                           (facts.CONFIGURATION, facts.MAX_SAMPLES_SUB),
                           *((facts.TRIGGER, k) for k in range(2, 7))):
            s.add_write_hook(index, sub, self._on_configuration)
        s.add_write_hook(facts.TRIGGER, facts.TRIGGER_VARIABLE, self._on_variable)

    # -- the objects ----------------------------------------------------------------------

    def _idle(self) -> None:
        if self.status & RecorderStatus.RUNNING:
            raise SdoAbortedError(ABORT_STATE)

    def _on_configuration(self, value: "Value") -> None:
        self._idle()

    def _on_variable(self, value: "Value") -> None:
        self._idle()
        try:
            where = facts.decode_variable(int(value))  # type: ignore[arg-type]
        except (ValueError, TypeError):
            raise SdoAbortedError(ABORT_RANGE) from None
        if where is not None:
            try:
                var = self.store.variable(*where)
            except SdoAbortedError:
                raise SdoAbortedError(ABORT_RANGE) from None
            if var.data_type not in _INTEGER_TYPES:
                raise SdoAbortedError(ABORT_RANGE)

    def _on_control(self, value: "Value") -> None:
        if value == Control.STOP:
            self.status &= ~RecorderStatus.RUNNING
        elif value in (Control.START, Control.START_FORCED):
            self._start(forced=value == Control.START_FORCED)
        else:
            raise SdoAbortedError(ABORT_RANGE)

    def _start(self, forced: bool) -> None:
        get = self.store.get_int
        self._channels = [facts.decode_variable(get(facts.VARIABLE_INDEX, k))
                          for k in range(1, facts.CHANNELS + 1)]
        self._trigger_var = facts.decode_variable(get(facts.TRIGGER, facts.TRIGGER_VARIABLE))
        self._period = get(facts.CONFIGURATION, facts.PERIOD_SUB) * facts.PERIOD_UNIT
        self._size = get(facts.CONFIGURATION, facts.MAX_SAMPLES_SUB)
        self._preceding = min(get(facts.TRIGGER, facts.PRECEDING), self._size - 1)
        self._mode = TriggerMode(get(facts.TRIGGER, facts.TRIGGER_MODE))
        self._high = get(facts.TRIGGER, facts.TRIGGER_HIGH)
        self._low = get(facts.TRIGGER, facts.TRIGGER_LOW)
        self._mask = get(facts.TRIGGER, facts.TRIGGER_MASK)
        self._forced = forced
        self._before = deque(maxlen=max(self._preceding, 1))
        self._after = []
        self._previous = None
        self._taken = 0
        self._t0 = self.now()
        self.status = RecorderStatus.RUNNING

    # -- sampling (called by the drive model) --------------------------------------------------

    @property
    def running(self) -> bool:
        return bool(self.status & RecorderStatus.RUNNING)

    def sample_times(self, until: float) -> Iterator[float]:
        """The sampling instants up to ``until`` not yet taken, in order; the caller takes
        each (:meth:`take`) before it asks for the next."""
        while self.running:
            t = self._t0 + self._taken * self._period
            if t > until + 1e-12:
                return
            yield t

    def take(self, t: float) -> None:
        """One sample of every channel, now (the drive stands at instant ``t``)."""
        if not self.running:
            return
        row = tuple(self._value(where) for where in self._channels)
        self._taken += 1
        if self.status & RecorderStatus.TRIGGERED:
            self._after.append(row)
        else:
            ready = len(self._before) >= self._preceding if self._preceding else True
            value = self._value(self._trigger_var)
            fire = ready and (self._forced or facts.triggered(
                self._mode, self._previous, value, self._high, self._low, self._mask))
            self._previous = value
            if fire:
                self.status |= RecorderStatus.TRIGGERED
                self._after.append(row)
            elif self._preceding:
                self._before.append(row)
        if len(self.samples) >= self._size:
            self.status &= ~RecorderStatus.RUNNING

    def _value(self, where: Optional[tuple[int, int]]) -> int:
        if where is None:
            return 0
        value = self.store.get(*where)
        if isinstance(value, bool):
            return int(value)
        if isinstance(value, int):
            return facts.signed32(value)
        if isinstance(value, float) and math.isfinite(value):
            return facts.signed32(int(value))
        return 0

    # -- the buffers ----------------------------------------------------------------------------

    @property
    def samples(self) -> list[tuple[int, ...]]:
        before = list(self._before) if self._preceding else []
        return before + self._after if self.status & RecorderStatus.TRIGGERED else before

    def buffer(self, channel: int) -> bytes:
        if channel >= len(self._channels) or self._channels[channel] is None:
            return b""
        return facts.encode_buffer([row[channel] for row in self.samples])
