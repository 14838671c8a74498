"""The readback side of one axis's motor record: polls, monitors, the alarm.

Every readback is a PSI read through :meth:`tcp_bridge.engine.Engine.execute`, like a
line on port 1912 (issue 33; the record's behaviour is epics-modules/motor
``motorRecord.cc``, the arithmetic :mod:`tcp_bridge.epics.record`). The motion runner
on top of it is :mod:`tcp_bridge.epics.axis`.

* **Reads.** A poll is R10, R12, R14, R82, R83 (R11 as well when a switch is hit or
  the drive is in fault) and, every :data:`SLOW_EVERY`-th poll, R05, R06, R26, R33,
  R34, R13 and R11 (speeds and limits set by any client). Polls run only while a CA
  client subscribes to a field of the record or a motion put waits, every
  :data:`MOVING_PERIOD` s while the axis moves and :data:`IDLE_PERIOD` s at rest; a
  read without a subscription refreshes once if the values are older than
  :data:`IDLE_PERIOD`. Transfers per axis per second: :func:`max_transfers_per_second`.
* **A poll is shared** by every caller that asks while it runs, unless a request of
  this record was answered after it began (its readback would be older).
* **Motion by others** (a PSI client's ``S00=1``) shows while somebody watches: DMOV 0
  while the drive runs, then VAL = RBV (``process()``: "make dmov track the state of
  movn", ``MIP_EXTERNAL``).
* **Alarm.** A read unanswered for :data:`OVERDUE` s raises COMM/INVALID at once; a
  refused request (NAK) raises STATE/MAJOR with its reason in ``-MsgTxt`` until a
  request of the record succeeds (``alarm_sub()``).
"""
from __future__ import annotations

import asyncio
import logging
import math
import time
from typing import Any, Awaitable, Callable, Dict, Optional, Tuple

from . import PutRefused
from . import fields as F
from .record import Frame, Sample, alarm, live_fields
from ..bus.sdo import NodeSilent
from ..tables.axes import DeviceCode
from ..errors import BridgeError, BusUnavailable, InvalidCommand, SilentLink
from ..tasks import cancel_and_wait
from ..wire import ReadRequest, Request, WriteRequest, decode_reply, format_value

log = logging.getLogger(__name__)

MOVING_PERIOD = 0.1  # s from poll to poll while the axis moves (or a motion put waits)
IDLE_PERIOD = 0.5  # s from poll to poll at rest, while someone subscribes
SLOW_EVERY = 10  # every 10th poll also reads speeds, limits and errors
OVERDUE = 0.4  # s: a read unanswered this long raises the COMM alarm (issue 33: "within a second")
# The state and "target reached" before the readback: a sample that says the motion
# ended has a position read after the drive said so (VAL = RBV at the end of a motion
# by others took 1.999 of a move to 2.0 when R12 came first, a loaded machine's poll).
FAST = (10, 82, 83, 12, 14)
SLOW = (5, 6, 26, 33, 34, 13, 11)
FAST_TRANSFERS = 6  # R82 costs 2 when bit 10 alone says "reached" (tcp_bridge.plan.reads)
SLOW_TRANSFERS = 11  # 05 06 26 33 34 13: one each; R11: 603Fh, 60FDh, (+3 on a limit error)
# motorRecord.cc's MIP bits (the "motion in progress" field).
MIP_HOME, MIP_MOVE, MIP_RETRY, MIP_STOP, MIP_EXTERNAL = 0x0008, 0x0020, 0x0040, 0x0200, 0x8000
# maxon EPOS4 Firmware Specification, "Statusword" (6041h) bit 15: position referenced
# to home position; set by a completed homing, cleared by the drive when it loses it
# (epos_link.cia402.SW.POSITION_REFERENCED). Manufacturer-specific: EPOS4 axes only.
REFERENCED = 1 << 15

# Nobody answered (a silent bus, link or node), as opposed to a drive that refused.
SILENCE = (BusUnavailable, SilentLink, NodeSilent, asyncio.TimeoutError)

Post = Callable[[Dict[str, Any]], Awaitable[None]]


def max_transfers_per_second(period: float = MOVING_PERIOD) -> float:
    """SDO transfers per axis per second at most while polled every ``period`` s (0 with
    PDO-fed status for the fast set; no polls at all when nobody subscribes)."""
    return (SLOW_EVERY * FAST_TRANSFERS + SLOW_TRANSFERS) / (SLOW_EVERY * period)


def reason(exc: BaseException) -> str:
    return str(exc) or type(exc).__name__


class Readbacks:
    """What the record of PSI axis ``addr`` knows, and how it reads the axis; the
    motion runner is :class:`tcp_bridge.epics.axis.AxisRecord`."""

    def __init__(self, engine: Any, addr: int, *, moving_period: float = MOVING_PERIOD,
                 idle_period: float = IDLE_PERIOD,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.engine = engine
        self.addr = addr
        self.moving_period = moving_period
        self.idle_period = idle_period
        self.clock = clock
        config = engine.table.axes[addr]
        self.values: Dict[str, Any] = {f.name: f.default for f in F.FIELDS}
        self.values.update({f.name: f.default for _, f in F.EXTRAS})
        mres = 1.0 / config.position_factor
        self.values.update(MRES=mres, ERES=mres, RRES=mres, RDBD=mres, UREV=mres * 200,
                           PREC=max(0, math.ceil(math.log10(config.position_factor))),
                           DESC=f"axis {addr} ({config.bus} node {config.node_id})"[:40],
                           OUT=f"tcp-bridge axis {addr}")
        self.post: Post = self._store
        self.sample = Sample()
        self.problem: Optional[str] = None  # the last refused request, until one succeeds
        self.homed = False  # MSTA's homed bit: the drive's (EPOS4), else our last homing's
        self.window = mres  # the drive's position window (R13), in dial units
        self.subscribers = 0
        self.external = False
        self.direction = 1
        self.polls = 0
        self.last_poll = -math.inf  # when the last poll ended
        self.poll_began = -math.inf  # when the last poll started (the pace of polls)
        self._polling: Optional["asyncio.Future[Sample]"] = None
        self._poll_gen = 0  # act_gen when the running poll began
        self.act_gen = 0  # requests of this record answered so far
        self._runner: Optional["asyncio.Task[None]"] = None
        self._watcher: Optional["asyncio.Task[None]"] = None
        self._closing = False

    @property
    def frame(self) -> Frame:
        v = self.values
        return Frame(float(v["OFF"]), -1 if v["DIR"] == "Neg" else 1, float(v["MRES"]))

    async def _store(self, changes: Dict[str, Any]) -> None:
        self.values.update(changes)

    # -- life ------------------------------------------------------------------------

    async def start(self) -> None:
        """Read the axis once (readback, limits, speeds): VAL = RBV, as init_record()."""
        sample = await self.poll(slow=True)
        if sample.position is not None:
            d = sample.position
            await self.post({"VAL": self.frame.user(d), "DVAL": d, "RVAL": self.frame.raw(d),
                             "LVAL": self.frame.user(d), "LDVL": d, "LRVL": self.frame.raw(d)})

    async def close(self) -> None:
        self._closing = True
        tasks = [t for t in (self._runner, self._watcher) if t is not None]
        if tasks:
            await cancel_and_wait(tasks, 5.0)
        self.release()

    def release(self) -> None:
        """Complete the puts that wait for a motion (the motion runner has them)."""

    def motion_owned(self) -> bool:
        """A motion of this record runs, or waits for SPMG Go (the runner says)."""
        return self._runner is not None

    def subscribed(self, count: int) -> None:
        """``count`` CA subscriptions to fields of this record now (0: stop polling)."""
        self.subscribers = count
        if self.subscribers and self._watcher is None and not self._closing:
            self._watcher = asyncio.ensure_future(self._watch())

    # -- requests ----------------------------------------------------------------------

    async def ask(self, cmd: int, value: Any = None) -> Optional[str]:
        """One PSI request of this axis; its reply's value (None for a write)."""
        request: Request = ReadRequest(self.addr, cmd) if value is None else \
            WriteRequest(self.addr, cmd, _text(value))
        return decode_reply(await self.engine.execute(request)).value

    async def act(self, *requests: Tuple[int, Any], why: str) -> bool:
        """Writes of one put, back to back; False if the drive or the bus refused them
        (NAK: the put itself completes, the record shows STATE/MAJOR); PutRefused if the
        PSI table refused a value (CAN: the CA put fails, ECA_PUTFAIL). Either way the
        reason goes to -MsgTxt and one line to the log (at -v, as the PSI ports' NAK
        and CAN reasons)."""
        try:
            await self.engine.execute_all(
                [WriteRequest(self.addr, cmd, _text(v)) for cmd, v in requests])
            self.act_gen += 1
        except InvalidCommand as exc:
            await self.refused(why, reason(exc))
            raise PutRefused(f"axis {self.addr}: {why}: {reason(exc)}") from None
        except (BridgeError, asyncio.TimeoutError) as exc:
            await self.refused(why, reason(exc))
            return False
        self.problem = None
        return True

    async def refused(self, why: str, text: str) -> None:
        """A request of this record was refused: one log line, the reason in -MsgTxt."""
        self.problem = f"{why}: {text}"
        log.info("EPICS axis %d: %s refused: %s", self.addr, why, text)
        await self._publish(self.sample)

    # -- polling -----------------------------------------------------------------------

    async def poll(self, slow: bool = False) -> Sample:
        """One poll, shared by every caller that asks while it runs, unless a request of
        this record was answered after it began (its readback would be older)."""
        while self._polling is not None:
            running, started = self._polling, self._poll_gen
            sample = await asyncio.shield(running)
            if started >= self.act_gen and not slow:
                return sample
        self._poll_gen = self.act_gen
        self.poll_began = self.clock()
        self._polling = asyncio.get_running_loop().create_future()
        try:
            sample = await self._read(slow or self.polls % SLOW_EVERY == 0)
            self._polling.set_result(sample)
            return sample
        except BaseException as exc:
            self._polling.set_exception(exc)
            self._polling.exception()  # retrieved: the callers that wait get it
            raise
        finally:
            self._polling = None

    async def _read(self, slow: bool) -> Sample:
        self.polls += 1
        got: Dict[int, Optional[str]] = {}
        failure: Optional[str] = None
        silent = False
        cmds = list(FAST + SLOW) if slow else list(FAST)
        loop = asyncio.get_running_loop()
        for cmd in cmds:
            # A read unanswered for OVERDUE seconds shows the alarm at once (an IOC's
            # driver does the same when its controller stops answering); the bus's own
            # verdict (tcp_bridge.bus.health) follows when its timeouts have run out.
            timer = loop.call_later(OVERDUE, self._schedule_overdue, cmd)
            try:
                got[cmd] = await self.ask(cmd)
            except (BridgeError, asyncio.TimeoutError) as exc:
                failure, silent = reason(exc), isinstance(exc, SILENCE)
                if cmd in FAST:
                    break  # the bus fails fast: the rest would be refused too
            finally:
                timer.cancel()
            if cmd == 83 and not slow and (got.get(83) == "1" or _fault(got.get(10))):
                cmds.append(11)  # which switch, or what fault
        self.last_poll = self.clock()
        sample = Sample(_int(got.get(10)), _float(got.get(12)), _float(got.get(14)),
                        _int(got.get(82)), _int(got.get(83)), _int(got.get(11)),
                        failure if failure and (12 not in got or 10 not in got) else None,
                        silent)
        if failure and sample.failure is None:
            log.info("axis %d: a slow read failed: %s", self.addr, failure)
        self.sample = sample
        await self._limits_and_speeds(got)
        await self._publish(sample)
        return sample

    def _schedule_overdue(self, cmd: int) -> None:
        asyncio.ensure_future(self._overdue(cmd))

    async def _overdue(self, cmd: int) -> None:
        if self._closing:
            return
        await self._publish(Sample(failure=f"axis {self.addr}: R{cmd:02d} unanswered for "
                                   f"{OVERDUE:g} s", silent=True))

    async def _limits_and_speeds(self, got: Dict[int, Optional[str]]) -> None:
        changes: Dict[str, Any] = {}
        dhlm, dllm = _float(got.get(33)), _float(got.get(34))
        if dhlm is not None and dllm is not None:
            hlm, llm = self.frame.user_limits(dhlm, dllm)
            changes.update(DHLM=dhlm, DLLM=dllm, HLM=hlm, LLM=llm)
        velo, acc, vmax = _float(got.get(5)), _float(got.get(6)), _float(got.get(26))
        if velo is not None:
            changes["VELO"] = abs(velo)
            changes["S"] = abs(velo) / float(self.values["UREV"])
            if acc:
                changes["ACCL"] = abs(velo) / abs(acc) if velo else self.values["ACCL"]
        if vmax is not None:
            changes.update(VMAX=abs(vmax), SMAX=abs(vmax) / float(self.values["UREV"]))
        window = _float(got.get(13))
        if window is not None:
            self.window = max(abs(window), float(self.values["MRES"]))
        if changes:
            await self.post({k: v for k, v in changes.items() if self.values.get(k) != v})

    async def pace(self, period: float) -> None:
        """Wait until ``period`` s after the last poll began: polls start at most once a
        period (the bound of :func:`max_transfers_per_second`), and a poll that takes a
        while does not stretch the period (as asyn's movingPollPeriod)."""
        await asyncio.sleep(max(0.0, self.poll_began + period - self.clock()))

    def referenced_bit(self) -> bool:
        """Whether the drive itself says it is homed: statusword bit 15 of an EPOS4."""
        return self.engine.axes[self.addr].device is DeviceCode.C_DC_MAXON_EPOS4

    async def _publish(self, sample: Sample) -> None:
        if sample.statusword is not None and self.referenced_bit():
            self.homed = bool(sample.statusword & REFERENCED)  # the drive decides
        live = live_fields(sample, self.frame, dval=float(self.values["DVAL"]),
                           homed=self.homed, problem=self.problem,
                           last_direction=self.direction)
        if "TDIR" in live:
            self.direction = 1 if live["TDIR"] else -1
        stat, sevr = alarm(sample, self.problem)
        live["STAT"], live["SEVR"] = F.STAT_MENU[stat], F.SEVR_MENU[sevr]
        await self.post({k: v for k, v in live.items() if self.values.get(k) != v})

    async def fresh(self) -> None:
        """Before a read nobody polls for: values at most :data:`IDLE_PERIOD` s old."""
        if self._watcher is None and self._runner is None \
                and self.clock() - self.last_poll > self.idle_period:
            await self.poll()

    async def _watch(self) -> None:
        """Poll while someone subscribes; track motion that others started."""
        try:
            while self.subscribers and not self._closing:
                if self._runner is not None:
                    await asyncio.sleep(self.moving_period)  # the runner polls
                    continue
                sample = await self.poll()
                if self.motion_owned():
                    pass  # paused: a motion of ours waits for SPMG Go, DMOV stays 0
                elif sample.moving and not self.external:
                    self.external = True
                    await self.post({"DMOV": 0, "MIP": MIP_EXTERNAL})
                elif self.external and not sample.moving:
                    self.external = False
                    await self._external_homing(sample)
                    await self._sync()
                    await self.post({"MIP": 0, "DMOV": 1})
                await self.pace(self.moving_period if sample.moving else self.idle_period)
        except asyncio.CancelledError:
            raise
        except Exception:
            log.exception("axis %d: EPICS poll failed", self.addr)
        finally:
            self._watcher = None

    async def _external_homing(self, sample: Sample) -> None:
        """After a motion another client started: was it a homing that ended well? The
        drive in homing mode (R15 = 6) with R82 = 1 is "homing attained" without error
        (tcp_bridge.plan.reads, CiA 402-2 6.6). An EPOS4 says it in every statusword."""
        if self.referenced_bit() or sample.reached != 1:
            return
        try:
            mode = await self.ask(15)
        except (BridgeError, asyncio.TimeoutError) as exc:
            log.info("EPICS axis %d: R15 after a motion by others: %s", self.addr, reason(exc))
            return
        if _int(mode) == 6:
            self.homed = True
            await self._publish(self.sample)

    async def _sync(self) -> None:
        """``syncTargetPosition()``: VAL, DVAL, RVAL (and the last ones) = the readback."""
        d = self.sample.position
        if d is None:
            return
        frame = self.frame
        u, r = frame.user(d), frame.raw(d)
        await self.post({"VAL": u, "DVAL": d, "RVAL": r, "LVAL": u, "LDVL": d, "LRVL": r,
                         "DIFF": 0.0, "RDIF": 0})


def _text(value: Any) -> str:
    if isinstance(value, bool):
        return str(int(value))
    if isinstance(value, int):
        return str(value)
    return format_value(float(value), 24)  # decimal, never an exponent (spec 2.2.1)


def _int(text: Optional[str]) -> Optional[int]:
    try:
        return None if text is None else int(text, 0)
    except ValueError:
        return None


def _float(text: Optional[str]) -> Optional[float]:
    try:
        return None if text is None else float(text)
    except ValueError:
        return None


def _fault(text: Optional[str]) -> bool:
    sw = _int(text)
    return sw is not None and bool(sw & 0x8)


__all__ = ["IDLE_PERIOD", "MOVING_PERIOD", "Readbacks", "max_transfers_per_second"]
