"""The Channel Access side of one record: caproto channels for every field of
:mod:`tcp_bridge.epics.fields`, wired to an :class:`~tcp_bridge.epics.axis.AxisRecord`.

* A put to a ``put`` field is handed to the record (:data:`PUTS` says which method);
  the channel's value changes only when the record posts it, so a client sees what
  the record made of its put (VAL back to its last value after a limit violation,
  STOP back to 0). The put's callback completes when the record's method returns:
  for a motion, at its end (``caproto``: ``verify_value`` is awaited before the
  WriteNotify response).
* ``live`` and ``fixed`` fields are read only (CA access rights), so a client's put is
  refused by its own CA library.
* Every channel of a record shares one :class:`caproto.ChannelAlarm`: STAT/SEVR of the
  record reach every field's monitors, as dbCommon's do in an IOC.
* A subscription to any field starts the record's polling; the last one going stops
  it (counted from caproto's subscription queues, ``ChannelData._queues``).
* Control limits as ``get_control_double()``: VAL/RBV carry HLM/LLM, DVAL/DRBV carry
  DHLM/DLLM, VELO carries VBAS..VMAX; units and precision from EGU and PREC
  (``get_units()``, ``get_precision()``).
"""
from __future__ import annotations

import asyncio
import math
from typing import Any, Awaitable, Callable, Dict, List, Tuple

from caproto import (AccessRights, ChannelAlarm, ChannelChar, ChannelData, ChannelDouble,
                     ChannelEnum, ChannelFloat, ChannelInteger, ChannelShort, ChannelString,
                     SkipWrite)

from caproto.server.common import HIGH_LOAD_TIMEOUT

from . import PutRefused
from . import fields as F
from .axis import AxisRecord

DRAIN = 2.0  # s at most that a put's completion waits for its monitor events to be queued
SEND_TURNS = 10  # loop turns for a circuit to send its batch once its window closed

_CONTROL = {"VAL": ("HLM", "LLM"), "RBV": ("HLM", "LLM"), "DVAL": ("DHLM", "DLLM"),
            "DRBV": ("DHLM", "DLLM"), "VELO": ("VMAX", "VBAS")}
_WATCHED = {"HLM", "LLM", "DHLM", "DLLM", "VMAX", "VBAS"}


class _Field:
    """What every field channel adds to caproto's: the record behind it."""

    record: AxisRecord
    owner: "RecordChannels"
    spec: F.Field
    on_put: Callable[[str, Any], Awaitable[None]]

    def check_access(self, hostname: str, username: str) -> AccessRights:
        if F.writable(self.spec):
            return AccessRights.READ | AccessRights.WRITE
        return AccessRights.READ

    async def verify_value(self, value: Any) -> Any:
        try:
            await self.on_put(self.spec.name, value)
        except PutRefused:
            raise  # the PSI table refused it: logged once, -MsgTxt says why
        except (ValueError, IndexError) as exc:  # a value the record cannot take
            await self.record.refused(f"{self.spec.name}: {_shown(value)}", str(exc))
            raise PutRefused(f"{self.owner.name}.{self.spec.name}: {exc}") from None
        await self.owner.drain()
        return SkipWrite  # the record posted what the put made (or nothing)

    async def subscribe(self, queue: Any, sub_spec: Any, sub: Any) -> None:
        await super().subscribe(queue, sub_spec, sub)  # type: ignore[misc]
        self.owner.recount()

    async def unsubscribe(self, queue: Any, sub_spec: Any) -> None:
        await super().unsubscribe(queue, sub_spec)  # type: ignore[misc]
        self.owner.recount()

    async def read(self, data_type: Any) -> Any:
        if self.spec.role == "live":
            await self.record.fresh()
        return await super().read(data_type)  # type: ignore[misc]


def _classes() -> Dict[F.Kind, type]:
    bases = {F.Kind.DOUBLE: ChannelDouble, F.Kind.FLOAT: ChannelFloat,
             F.Kind.SHORT: ChannelShort, F.Kind.LONG: ChannelInteger,
             F.Kind.ENUM: ChannelEnum, F.Kind.STRING: ChannelString, F.Kind.CHARS: ChannelChar}
    return {kind: type(f"Record{base.__name__}", (_Field, base), {})
            for kind, base in bases.items()}


_CLASSES = _classes()


def _initial(spec: F.Field, value: Any) -> Any:
    if spec.kind is F.Kind.ENUM:
        return value if isinstance(value, str) else spec.menu[int(value)]
    if spec.kind in (F.Kind.STRING, F.Kind.CHARS):
        return str(value)
    if spec.kind in (F.Kind.SHORT, F.Kind.LONG):
        return int(value)
    return float(value)


class RecordChannels:
    """The channels of one record, by PV name, and the post function of the record."""

    def __init__(self, record: AxisRecord, name: str) -> None:
        self.record = record
        self.name = name
        self.alarm = ChannelAlarm()
        self.by_field: Dict[str, ChannelData] = {}
        self.pvdb: Dict[str, ChannelData] = {}
        record.values["NAME"] = name
        for spec in F.FIELDS:
            self._add(f"{name}.{spec.name}", spec)
        self.pvdb[name] = self.by_field["VAL"]  # the record's own name is its VAL
        for suffix, spec in F.EXTRAS:
            self._add(f"{name}{suffix}", spec)
        self.context: Any = None  # the caproto Context, set by tcp_bridge.epics.server
        record.post = self.post

    def _add(self, pv: str, spec: F.Field) -> None:
        cls = _CLASSES[spec.kind]
        value = _initial(spec, self.record.values[spec.name])
        kwargs: Dict[str, Any] = {"value": value, "alarm": self.alarm,
                                  "reported_record_type": "motor"}
        if spec.kind is F.Kind.ENUM:
            kwargs["enum_strings"] = spec.menu[:16]  # CA carries at most 16 (STAT: the first 16)
        elif spec.kind is F.Kind.CHARS:
            kwargs["max_length"] = F.MESSAGE_SIZE
        elif spec.kind in (F.Kind.DOUBLE, F.Kind.FLOAT):
            kwargs["precision"] = int(self.record.values["PREC"])
            kwargs["units"] = _units(spec.name, str(self.record.values["EGU"]))
        channel = cls(**kwargs)
        channel.record = self.record
        channel.owner = self
        channel.spec = spec
        channel.on_put = self._put
        self.by_field[spec.name] = channel
        self.pvdb[pv] = channel

    async def drain(self) -> None:
        """Let the monitor events a put caused go out before its completion does, as a
        client reads them right after (pyepics ``Motor.move`` reads LVIO then).

        caproto moves an event from the context's queue to each circuit's queue, and a
        circuit sends what it took once ``HIGH_LOAD_TIMEOUT`` (10 ms) passed without a
        new event. So: both queues empty (bounded by :data:`DRAIN`), then that window,
        then a few turns of the loop for the circuit's timed-out get and its send. The
        circuit's window began before ours (it took the last event before we saw its
        queue empty), so its timer fires first; the turns are counted in loop turns, not
        time, so a loaded machine cannot reorder them. The context's queue was not
        looked at before: under load its events were still there when the completion
        went out, and ``Motor.move`` returned 0 for a move refused with LVIO = 1."""
        context = self.context
        if context is None:
            return
        loop = asyncio.get_running_loop()
        deadline = loop.time() + DRAIN

        def queued() -> bool:
            return not context.subscription_queue.empty() or any(
                not c.subscription_queue.empty() for c in list(context.circuits))

        while loop.time() < deadline and queued():
            await asyncio.sleep(0.002)
        await asyncio.sleep(HIGH_LOAD_TIMEOUT + 0.002)
        for _ in range(SEND_TURNS):
            await asyncio.sleep(0)

    def recount(self) -> None:
        """Subscriptions to any field of the record, from caproto's own bookkeeping
        (``ChannelData._queues``: queue -> sync -> data type -> subscription specs)."""
        count = sum(len(specs) for channel in set(self.by_field.values())
                    for syncs in channel._queues.values() for types in syncs.values()
                    for specs in types.values())
        self.record.subscribed(count)

    # -- record -> clients ---------------------------------------------------------

    async def post(self, changes: Dict[str, Any]) -> None:
        """Write each changed field to its channel, in the order given; STAT/SEVR as the
        record's alarm (published to every field's monitors).

        Control limits, units and precision are in place before any value's monitor
        goes out, as in an IOC, where ``get_control_double()`` reads HLM/LLM that the
        record set before ``db_post_events``: ophyd's ``EpicsMotor`` answers an HLM or
        LLM monitor with a fresh DBR_CTRL get of VAL, and got the old limit (for ever,
        as nothing changes them again) when that get came between the two."""
        values = self.record.values
        values.update(changes)
        if _WATCHED & changes.keys() or {"EGU", "PREC"} & changes.keys():
            await self._metadata(changes)
        alarm_change = {}
        for name, value in changes.items():
            channel = self.by_field.get(name)
            if channel is None:
                continue
            spec = channel.spec  # type: ignore[attr-defined]
            if name == "MsgTxt":
                value = str(value)[:F.MESSAGE_SIZE - 1]
            await channel.write(_initial(spec, value), verify_value=False)
            if name in ("STAT", "SEVR"):
                alarm_change[name] = spec.menu.index(value) if isinstance(value, str) else value
        if alarm_change:
            await self.alarm.write(status=alarm_change.get("STAT", self.alarm.status),
                                   severity=alarm_change.get("SEVR", self.alarm.severity))

    async def _metadata(self, changes: Dict[str, Any]) -> None:
        v = self.record.values
        for name, (high, low) in _CONTROL.items():
            hi, lo = float(v[high]), float(v[low])
            if not (math.isfinite(hi) and math.isfinite(lo)):
                continue
            await self.by_field[name].write_metadata(
                upper_ctrl_limit=hi, lower_ctrl_limit=lo, upper_disp_limit=hi,
                lower_disp_limit=lo)
        if {"EGU", "PREC"} & changes.keys():
            for spec in F.FIELDS:
                if spec.kind in (F.Kind.DOUBLE, F.Kind.FLOAT):
                    await self.by_field[spec.name].write_metadata(
                        units=_units(spec.name, str(v["EGU"])), precision=int(v["PREC"]))

    # -- clients -> record ---------------------------------------------------------

    async def _put(self, name: str, value: Any) -> None:
        spec = F.BY_NAME.get(name) or dict((s.name, s) for _, s in F.EXTRAS)[name]
        if spec.kind in (F.Kind.DOUBLE, F.Kind.FLOAT, F.Kind.SHORT, F.Kind.LONG):
            if not math.isfinite(float(value)):
                raise ValueError(f"{self.name}.{name}: {value!r} is not a finite number")
        handler = PUTS.get(name)
        if handler is None:  # a "meta" field: the record keeps it
            await self.post({name: value})
            return
        await handler(self.record, value)


async def _val(r: AxisRecord, v: Any) -> None:
    await r.move(r.frame.dial(float(v)), "VAL")


async def _dval(r: AxisRecord, v: Any) -> None:
    await r.move(float(v), "DVAL")


async def _rval(r: AxisRecord, v: Any) -> None:
    await r.move(int(v) * float(r.values["MRES"]), "RVAL")


async def _rlv(r: AxisRecord, v: Any) -> None:
    target = float(r.values["VAL"]) + float(v)
    await r.post({"RLV": 0.0, "LRLV": float(v)})
    await r.move(r.frame.dial(target), "RLV")


def _tweak(sign: int, field: str) -> Callable[[AxisRecord, Any], Awaitable[None]]:
    async def tweak(r: AxisRecord, v: Any) -> None:
        if not int(v):
            return
        target = float(r.values["VAL"]) + sign * float(r.values["TWV"])
        try:
            await r.move(r.frame.dial(target), field)
        finally:
            await r.post({field: 0})
    return tweak


async def _stop(r: AxisRecord, v: Any) -> None:
    if int(v):
        await r.stop()


async def _spmg(r: AxisRecord, v: Any) -> None:
    await r.spmg(F.SPMG_MENU[F.menu_index(F.BY_NAME["SPMG"], v)])


def _home(field: str) -> Callable[[AxisRecord, Any], Awaitable[None]]:
    async def home(r: AxisRecord, v: Any) -> None:
        if int(v):
            await r.home(field)
    return home


def _enable(field: str) -> Callable[[AxisRecord, Any], Awaitable[None]]:
    async def enable(r: AxisRecord, v: Any) -> None:
        on = F.menu_index(F.BY_NAME["CNEN"], v) if isinstance(v, str) else int(v)
        if await r.act((4, 1 if on else 0), why=f"{field}: {'enable' if on else 'disable'}"):
            await r.poll()
    return enable


async def _reset(r: AxisRecord, v: Any) -> None:
    if int(v) and await r.act((17, 1), why="Reset: fault reset"):
        await r.poll(slow=True)


async def _sync(r: AxisRecord, v: Any) -> None:
    if int(v) and r.values["MIP"] == 0:
        await r.poll()
        await r._sync()
    await r.post({"SYNC": 0})


async def _off(r: AxisRecord, v: Any) -> None:
    await r.post({"OFF": float(v)})
    await r._recompute()


async def _dir(r: AxisRecord, v: Any) -> None:
    old = r.frame
    new = F.DIR_MENU[F.menu_index(F.BY_NAME["DIR"], v)]
    if r.values["FOFF"] == "Variable":  # special() DIR: keep VAL, move OFF
        off = float(r.values["VAL"]) - float(r.values["DVAL"]) * (-1 if new == "Neg" else 1)
        await r.post({"DIR": new, "OFF": off})
    else:
        await r.post({"DIR": new})
    del old
    await r._recompute()


def _menu(field: str) -> Callable[[AxisRecord, Any], Awaitable[None]]:
    async def put(r: AxisRecord, v: Any) -> None:
        spec = F.BY_NAME[field]
        await r.post({field: spec.menu[F.menu_index(spec, v)]})
    return put


def _switch(field: str, value: str, own: str) -> Callable[[AxisRecord, Any], Awaitable[None]]:
    async def put(r: AxisRecord, v: Any) -> None:
        await r.post({field: value, own: 0})
    return put


def _user_limit(field: str) -> Callable[[AxisRecord, Any], Awaitable[None]]:
    async def put(r: AxisRecord, v: Any) -> None:
        dial_field, dial = r.frame.dial_limit_of_user(field, float(v))
        await r.dial_limit(dial_field, dial)
    return put


def _dial_limit(field: str) -> Callable[[AxisRecord, Any], Awaitable[None]]:
    async def put(r: AxisRecord, v: Any) -> None:
        await r.dial_limit(field, float(v))
    return put


async def _velo(r: AxisRecord, v: Any) -> None:
    velo = abs(float(v))
    vmax = float(r.values["VMAX"])
    if vmax > 0:
        velo = min(velo, vmax)  # special() VELO: range_check(velo, vbas, vmax)
    accl = float(r.values["ACCL"]) or 0.1
    if await r.act((5, velo), (6, velo / accl), why=f"VELO: set {velo:g}"):
        await r.poll(slow=True)


async def _accl(r: AxisRecord, v: Any) -> None:
    accl = float(v) if float(v) > 0 else 0.1  # special() ACCL: 0.1 when not positive
    velo = float(r.values["VELO"])
    if velo > 0 and await r.act((6, velo / accl), why=f"ACCL: set {accl:g}"):
        await r.post({"ACCL": accl})
        await r.poll(slow=True)


async def _vmax(r: AxisRecord, v: Any) -> None:
    if await r.act((26, abs(float(v))), why=f"VMAX: set {abs(float(v)):g}"):
        await r.poll(slow=True)


PUTS: Dict[str, Callable[[AxisRecord, Any], Awaitable[None]]] = {
    "VAL": _val, "DVAL": _dval, "RVAL": _rval, "RLV": _rlv,
    "TWF": _tweak(1, "TWF"), "TWR": _tweak(-1, "TWR"), "STOP": _stop, "SPMG": _spmg,
    "HOMF": _home("HOMF"), "HOMR": _home("HOMR"), "CNEN": _enable("CNEN"), "Enable": _enable(":Enable"),
    "Reset": _reset, "SYNC": _sync, "OFF": _off, "DIR": _dir,
    "SET": _menu("SET"), "FOFF": _menu("FOFF"),
    "SSET": _switch("SET", "Set", "SSET"), "SUSE": _switch("SET", "Use", "SUSE"),
    "FOF": _switch("FOFF", "Frozen", "FOF"), "VOF": _switch("FOFF", "Variable", "VOF"),
    "HLM": _user_limit("HLM"), "LLM": _user_limit("LLM"),
    "DHLM": _dial_limit("DHLM"), "DLLM": _dial_limit("DLLM"),
    "VELO": _velo, "ACCL": _accl, "VMAX": _vmax,
}
"""The put of each ``put`` field (its docstring in :mod:`tcp_bridge.epics.axis`)."""
assert {f.name for f in F.FIELDS if f.role == "put"} | {"Enable", "Reset"} == set(PUTS)


def _shown(value: Any) -> str:
    """A put's value as the log shows it: the one element of a CA array, as text."""
    if hasattr(value, "tolist"):
        value = value.tolist()
    if isinstance(value, (list, tuple)) and len(value) == 1:
        value = value[0]
    if isinstance(value, bytes):
        value = value.decode("latin-1")
    return repr(value) if isinstance(value, str) else f"{value:g}" \
        if isinstance(value, float) else str(value)


def _units(field: str, egu: str) -> str:
    """``get_units()``: speeds in EGU/sec, ACCL in sec, the rest in EGU."""
    if field in ("VELO", "VMAX", "BVEL", "VBAS", "JVEL", "HVEL"):
        return f"{egu}/sec"[:8]
    if field in ("ACCL", "BACC"):
        return "sec"
    return egu[:8]


def build(records: List[Tuple[AxisRecord, str]]) -> Tuple[Dict[str, ChannelData],
                                                           List[RecordChannels]]:
    """The pvdb of every record: ``[(record, full record name), ...]``."""
    pvdb: Dict[str, ChannelData] = {}
    all_channels = []
    for record, name in records:
        channels = RecordChannels(record, name)
        pvdb.update(channels.pvdb)
        all_channels.append(channels)
    return pvdb, all_channels
