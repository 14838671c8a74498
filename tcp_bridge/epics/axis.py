"""One axis served as a motor record: the motion runner. Every put becomes PSI requests
through :meth:`tcp_bridge.engine.Engine.execute` like a line on port 1912; the reads,
monitors and alarm are :mod:`tcp_bridge.epics.readback`.

Rules (issue 33; the record's behaviour is epics-modules/motor ``motorRecord.cc``,
R6.9 to R6.96, cited by function; the arithmetic is :mod:`tcp_bridge.epics.record`):

* **One pipeline.** A put is resolved in the order the record acts on it, against the
  one state per axis every client shares; a move is ``S02`` (dial target) and
  ``S00=1`` resolved back to back (:meth:`~tcp_bridge.engine.Engine.execute_all`), so
  no other client's request falls between them; a stop is ``S00=8``. Nothing here
  talks to a drive.
* **DMOV** goes 1 -> 0 when a motion put arrives (``special()``, "Blink .dmov") and
  back to 1 once, after the last readback of the motion (``process()``: "DMOV going
  true before last readback update" was a bug), a zero-length move included
  (``do_work()``: ``too_small`` sends nothing and sets DMOV). Every put that waits for
  the motion completes then, never before (``process()`` calls ``recGblFwdLink()``,
  which completes the record's put-notify, only when DMOV is 1). VAL itself is posted
  at once.
* **A new target while our move runs** (``process()``, "Test for new target position
  in opposite direction of current motion", NTM = YES): at each readback, when the
  axis runs away from the newest target (the sign of target - readback is not CDIR)
  by more than NTMF x (|BDST| + RDBD), the record sends a stop, and when the axis is at
  rest the move to the newest target (``process()``: "pp" cleared, so no
  ``postProcess()``: VAL stays the new target). A new target the axis is still
  running towards is taken when the running move ends (``process()``: "new target
  position while MIP != DONE"). DMOV stays 0 throughout and every waiting put
  (the first one's too) completes when the final move ended. One difference:
  EPICS base holds a second put *with callback* until the first completed (dbNotify.c
  ``processNotifyCommon()``: "Another processNotify owns the record"), so an IOC only
  retargets on a put without callback; here both act at once (caproto runs each
  write in its own task) and complete together.
* **STOP** (and SPMG Stop) sends ``S00=8`` at once, drops targets not yet sent, and
  when the axis is at rest VAL = RBV (``do_work()``: "STOP means make the motor stop
  and, when it does, make the drive fields agree with the readback fields").
  A motion that ended outside the drive's position window (R13) of its target
  (stopped by another client or a fault) also gets VAL = RBV (**chosen**: the record
  cannot tell who stopped it).
* **SPMG** (``do_work()``'s comment): *Pause* stops the axis (``S00=8``) and keeps
  VAL: the motion is not over (DMOV stays 0, MIP = RETRY, puts wait, as the record
  with retries does: ``maybeRetry()``), and a new target while paused is only kept;
  *Go* moves to VAL; *Move* moves once, then goes to Pause (``maybeRetry()``: "If
  motion was initiated by "Move" button, pause"); *Stop* is STOP.
"""
from __future__ import annotations

import asyncio
import logging
from dataclasses import dataclass
from typing import Any, Dict, List, Optional

from . import PutRefused
from . import fields as F
from .readback import (IDLE_PERIOD, MIP_HOME, MIP_MOVE, MIP_RETRY, MIP_STOP, MOVING_PERIOD,
                       Readbacks, _float, max_transfers_per_second)
from .record import Sample, runs_away, too_small, violates

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Target:
    """One motion a put asked for: a move to dial ``dval``, or a homing."""

    kind: str  # "move" or "home"
    dval: float
    field: str  # the field whose put asked for it, for the log and -MsgTxt


class AxisRecord(Readbacks):
    """The motor record of PSI axis ``addr``: :class:`Readbacks` and the motion runner."""

    def __init__(self, engine: Any, addr: int, **kw: Any) -> None:
        super().__init__(engine, addr, **kw)
        self.pending: Optional[Target] = None  # the newest target not sent yet
        self.running: Optional[Target] = None  # the one the drive runs for us
        self.cdir = 1  # commanded direction of the running move (CDIR)
        self.waiters: List["asyncio.Future[None]"] = []  # puts waiting for the motion's end
        self.stop_gen = 0
        self.stopped = False

    def motion_owned(self) -> bool:
        return self._runner is not None or self.pending is not None

    def release(self) -> None:
        waiters, self.waiters = self.waiters, []
        for fut in waiters:
            if not fut.done():
                fut.set_result(None)

    # -- motion ------------------------------------------------------------------------

    async def move(self, dval: float, field: str = "VAL") -> None:
        """A put to VAL, DVAL, RVAL, RLV, TWF or TWR; returns when the motion ended."""
        frame = self.frame
        if self.values["DMOV"] == 1:
            await self.post({"DMOV": 0})  # special(): blink DMOV
        if self.values["SET"] == "Set":
            await self._set_position(dval)
            return
        await self.post({"VAL": frame.user(dval), "DVAL": dval, "RVAL": frame.raw(dval)})
        v = self.values
        if violates(dval, float(v["LDVL"]), float(v["DHLM"]), float(v["DLLM"])):
            await self.post({"VAL": v["LVAL"], "DVAL": v["LDVL"], "RVAL": v["LRVL"],
                             "LVIO": 1})
            if not self.motion_owned():
                await self.post({"DMOV": 1})
            return
        if v["LVIO"]:
            await self.post({"LVIO": 0})
        await self._motion(Target("move", dval, field))

    async def home(self, field: str) -> None:
        """HOMF or HOMR: the axis's homing (S00=9, its method is 40); returns at its end."""
        await self.post({field: 1})
        if self.values["DMOV"] == 1:
            await self.post({"DMOV": 0})
        await self._motion(Target("home", 0.0, field))

    async def _motion(self, target: Target) -> None:
        fut: "asyncio.Future[None]" = asyncio.get_running_loop().create_future()
        self.waiters.append(fut)
        self.pending = target
        if self.values["SPMG"] in ("Stop", "Pause"):
            if self.values["MIP"] == 0:
                await self.post({"MIP": MIP_RETRY})
            # do_work(): "IF Stop/Pause/Move/Go field set to STOP, OR, PAUSE: NORMAL
            # RETURN": kept until SPMG goes to Go (or Move)
        elif self._runner is None:
            self._runner = asyncio.ensure_future(self._run())
        await fut

    async def _run(self) -> None:
        try:
            while self.pending is not None and self.values["SPMG"] not in ("Stop", "Pause"):
                target, self.pending = self.pending, None
                self.running = target
                if target.kind == "move":
                    await self._one_move(target)
                else:
                    await self._one_home(target)
                self.running = None
        except asyncio.CancelledError:
            raise
        except PutRefused:
            pass  # a target the PSI table refused: act() logged it, -MsgTxt says why
        except Exception:
            log.exception("axis %d: EPICS motion failed", self.addr)
        finally:
            self.running = None
            self._runner = None
            if not self._closing:
                await self._end()

    async def _one_move(self, target: Target) -> None:
        gen = self.stop_gen
        sample = await self.poll()  # the drive decides: where it is now
        if sample.position is not None and too_small(target.dval, sample.position,
                                                     float(self.values["MRES"])):
            await self._remember(target.dval)
            return
        if gen != self.stop_gen:
            return  # a stop arrived meanwhile: it is the last word
        self.cdir = int(target.dval >= (sample.position or 0.0))
        await self.post({"MIP": MIP_MOVE, "CDIR": self.cdir})
        self.stopped = False
        if await self.act((2, target.dval), (0, 1),
                          why=f"{target.field}: move to {target.dval:g}"):
            await self._remember(target.dval)
            await self._until_rest(ntm=True)

    async def _one_home(self, target: Target) -> None:
        gen = self.stop_gen
        await self.post({"MIP": MIP_HOME})
        if gen == self.stop_gen and await self.act((0, 9), why=f"{target.field}: homing"):
            sample = await self._until_rest()
            if not self.referenced_bit():  # else the drive's statusword says it
                self.homed = sample.reached == 1 and not sample.homing_failed \
                    and not self.stopped
        await self.post({"HOMF": 0, "HOMR": 0})
        await self._sync()

    async def _until_rest(self, ntm: bool = False) -> Sample:
        stopping = False
        while True:
            await self.pace(self.moving_period)
            sample = await self.poll()
            if not sample.moving:
                return sample
            if ntm and not stopping and self._runs_away(sample):
                stopping = True  # process(): "(pmr->mip & MIP_STOP) == 0", one stop
                new = self.pending
                assert new is not None
                await self.post({"MIP": MIP_MOVE | MIP_STOP})
                await self.act((0, 8), why=f"{new.field}: new target {new.dval:g} behind "
                               "the running move, stop first")

    def _runs_away(self, sample: Sample) -> bool:
        """``process()``'s new target monitor (:func:`~tcp_bridge.epics.record.runs_away`)
        for the newest target not sent yet, with NTM = YES."""
        v, new = self.values, self.pending
        if new is None or new.kind != "move" or sample.position is None \
                or F.menu_index(F.BY_NAME["NTM"], v["NTM"]) != F.YESNO_MENU.index("YES"):
            return False
        return runs_away(new.dval, sample.position, self.cdir, mres=float(v["MRES"]),
                         ntmf=float(v["NTMF"]), bdst=float(v["BDST"]), rdbd=float(v["RDBD"]))

    async def _remember(self, dval: float) -> None:
        frame = self.frame
        await self.post({"LVAL": frame.user(dval), "LDVL": dval, "LRVL": frame.raw(dval)})

    async def _end(self) -> None:
        """The runner stopped: paused (the motion goes on at Go), a target left (a refused
        one ended the runner), or the end of the motion."""
        if self.pending is not None and not self._closing:
            if self.values["SPMG"] in ("Stop", "Pause"):
                await self.poll()
                await self.post({"MIP": MIP_RETRY})  # maybeRetry(): RETRY, DMOV stays 0
                return
            self._runner = asyncio.ensure_future(self._run())
            return
        await self._finish()

    async def _finish(self) -> None:
        """The end of a motion: last readback, VAL = RBV if it was stopped, then DMOV."""
        sample = await self.poll()
        dval = float(self.values["DVAL"])
        off_target = sample.position is not None and abs(sample.position - dval) > self.window
        if self.stopped or off_target:
            await self._sync()
        self.stopped = False
        changes: Dict[str, Any] = {"MIP": 0}
        if self.values["SPMG"] == "Move":  # maybeRetry(): "If motion was initiated by
            changes["SPMG"] = changes["LSPG"] = "Pause"  # "Move" button, pause."
        await self.post(changes)
        await self.post({"DMOV": 1})
        self.release()

    async def stop(self, field: str = "STOP", sync_at_rest: bool = False) -> None:
        """STOP = 1 or SPMG Stop: S00=8 at once; targets not yet sent are dropped."""
        self.stop_gen += 1
        self.pending = None
        self.stopped = self._runner is not None
        await self.act((0, 8), why=f"{field}: stop")
        if self._runner is None and (self.waiters or sync_at_rest):
            # At rest: VAL = RBV (do_work(): not moving, "syncTargetPosition()"). Puts
            # waiting for Go (paused) end here (do_work(): MIP RETRY -> DONE, DMOV TRUE).
            await self.poll()
            await self._sync()
            if self.waiters:
                await self.post({"MIP": 0, "DMOV": 1})
                self.release()
        await self.post({"STOP": 0})

    async def spmg(self, value: str) -> None:
        await self.post({"SPMG": value, "LSPG": value})
        if value == "Stop":
            await self.stop("SPMG", sync_at_rest=True)
        elif value == "Pause":
            self.stop_gen += 1  # a move not sent yet is not sent now
            if self.pending is None and self.running is not None:
                self.pending = self.running  # Go moves to VAL again
            await self.act((0, 8), why="SPMG: pause")
        elif self.pending is not None and self._runner is None:
            self._runner = asyncio.ensure_future(self._run())  # Go or Move: carry on

    async def _set_position(self, dval_or_user: float) -> None:
        """SET mode: a new VAL/DVAL redefines the position, nothing moves (``do_work()``:
        FOFF Variable changes OFF; Frozen loads a new dial position: here the PSI
        offset 25, so that R12 reads it as well)."""
        v, frame = self.values, self.frame
        if v["FOFF"] == "Variable":
            user = frame.user(dval_or_user)
            off = user - float(v["DVAL"]) * frame.dir
            await self.post({"OFF": off})
            await self._recompute()
        else:
            sample = await self.poll()
            if sample.position is not None:
                offset = _float(await self.ask(25)) or 0.0
                await self.act((25, offset + dval_or_user - sample.position),
                               why="VAL: set the dial position")
                await self.poll(slow=True)
                await self._sync()
        await self.post({"DMOV": 1})

    async def _recompute(self) -> None:
        """After OFF or DIR changed: VAL, RBV and the user limits (``special()``)."""
        v, frame = self.values, self.frame
        hlm, llm = frame.user_limits(float(v["DHLM"]), float(v["DLLM"]))
        await self.post({"VAL": frame.user(float(v["DVAL"])),
                         "LVAL": frame.user(float(v["LDVL"])),
                         "RBV": frame.user(float(v["DRBV"])), "HLM": hlm, "LLM": llm})

    async def dial_limit(self, field: str, value: float) -> None:
        """DHLM or DLLM: the drive's limit (23/24 in drive direction, 33/34 read back)."""
        inversion = int(float(await self.ask(22) or 1))
        offset = _float(await self.ask(25)) or 0.0
        drive_side = value - offset
        high = (field == "DHLM") == (inversion == 1)
        await self.act((23 if high else 24, drive_side * inversion), why=f"{field}: set {value:g}")
        await self.poll(slow=True)


__all__ = ["AxisRecord", "IDLE_PERIOD", "MOVING_PERIOD", "max_transfers_per_second"]
