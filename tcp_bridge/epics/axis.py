"""One axis served as a motor record: the motion runner. Every put becomes PSI requests
through :meth:`tcp_bridge.engine.Engine.execute` like a line on port 1912; the reads,
monitors and alarm are :mod:`tcp_bridge.epics.readback`.

Rules (issue 33; the record's behaviour is epics-modules/motor ``motorRecord.cc``,
the arithmetic is :mod:`tcp_bridge.epics.record`):

* **One pipeline.** A put is resolved in the order the record acts on it, against the
  one state per axis every client shares; a move is ``S02`` (dial target) and
  ``S00=1`` resolved back to back (:meth:`~tcp_bridge.engine.Engine.execute_all`), so
  no other client's request falls between them. Nothing here talks to a drive.
* **DMOV** goes 1 -> 0 when a motion put arrives (``special()``, "Blink .dmov") and
  back to 1 once, after the last readback of the motion (``process()``: "DMOV going
  true before last readback update" was a bug), a zero-length move included
  (``do_work()``: ``too_small`` sends nothing and sets DMOV). A put to VAL with
  callback completes then, never before; VAL itself is posted at once.
* **Moves in flight.** A new target while the axis moves is taken when the running
  move ends (``process()``: "new target position while MIP != DONE"), so the put of
  each completes when the last one ended. A STOP (or SPMG Stop/Pause) is sent at once
  as ``S00=8`` and cancels targets not yet sent. After a stop, or a motion that ended
  outside the drive's position window (R13) of its target (stopped by another client
  or a fault), VAL = RBV (``postProcess()``, ``syncTargetPosition()``; the second case
  is **chosen**: the record cannot tell who stopped it).
"""
from __future__ import annotations

import asyncio
import logging
from typing import Any, Dict, Tuple

from .readback import (IDLE_PERIOD, MIP_HOME, MIP_MOVE, MOVING_PERIOD, Readbacks,
                       _float, max_transfers_per_second)
from .record import Sample, too_small, violates

log = logging.getLogger(__name__)


class AxisRecord(Readbacks):
    """The motor record of PSI axis ``addr``: :class:`Readbacks` and the motion runner."""

    # -- motion ------------------------------------------------------------------------

    async def move(self, dval: float) -> None:
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
            if self._runner is None and self.pending is None:
                await self.post({"DMOV": 1})
            return
        if v["LVIO"]:
            await self.post({"LVIO": 0})
        await self._motion(("move", dval))

    async def home(self, field: str) -> None:
        """HOMF or HOMR: the axis's homing (S00=9, its method is 40); returns at its end."""
        await self.post({field: 1})
        if self.values["DMOV"] == 1:
            await self.post({"DMOV": 0})
        await self._motion(("home", 0.0))

    async def _motion(self, what: Tuple[str, float]) -> None:
        fut: "asyncio.Future[None]" = asyncio.get_running_loop().create_future()
        self.waiters.append(fut)
        self.pending = what
        if self.values["SPMG"] in ("Stop", "Pause"):
            pass  # do_work(): kept until SPMG goes to Go (or Move)
        elif self._runner is None:
            self._runner = asyncio.ensure_future(self._run())
        await fut

    async def _run(self) -> None:
        try:
            while self.pending is not None and self.values["SPMG"] not in ("Stop", "Pause"):
                kind, dval = self.pending
                self.pending = None
                if kind == "move":
                    await self._one_move(dval)
                else:
                    await self._one_home()
        except asyncio.CancelledError:
            raise
        except Exception:
            log.exception("axis %d: EPICS motion failed", self.addr)
        finally:
            self._runner = None
            if not self._closing:
                await self._finish()

    async def _one_move(self, dval: float) -> None:
        gen = self.stop_gen
        sample = await self.poll()  # the drive decides: where it is now
        if sample.position is not None and too_small(dval, sample.position,
                                                     float(self.values["MRES"])):
            await self._remember(dval)
            return
        if gen != self.stop_gen:
            return  # a stop arrived meanwhile: it is the last word
        await self.post({"MIP": MIP_MOVE, "CDIR": int(dval >= (sample.position or 0.0))})
        self.stopped = False
        if await self.act((2, dval), (0, 1), why=f"move to {dval:g}"):
            await self._remember(dval)
            await self._until_rest()

    async def _one_home(self) -> None:
        gen = self.stop_gen
        await self.post({"MIP": MIP_HOME})
        if gen == self.stop_gen and await self.act((0, 9), why="homing"):
            sample = await self._until_rest()
            self.homed = sample.reached == 1 and not sample.homing_failed \
                and not self.stopped
        await self.post({"HOMF": 0, "HOMR": 0})
        await self._sync()

    async def _until_rest(self) -> Sample:
        while True:
            await asyncio.sleep(self.moving_period)
            sample = await self.poll()
            if not sample.moving:
                return sample

    async def _remember(self, dval: float) -> None:
        frame = self.frame
        await self.post({"LVAL": frame.user(dval), "LDVL": dval, "LRVL": frame.raw(dval)})

    async def _finish(self) -> None:
        """The end of a motion: last readback, VAL = RBV if it was stopped, then DMOV."""
        sample = await self.poll()
        dval = float(self.values["DVAL"])
        off_target = sample.position is not None and abs(sample.position - dval) > self.window
        if self.stopped or off_target:
            await self._sync()
        spmg = self.values["SPMG"]
        changes: Dict[str, Any] = {"MIP": 0}
        if spmg == "Move":  # maybeRetry(): "If motion was initiated by "Move" button, pause."
            changes["SPMG"] = changes["LSPG"] = "Pause"
        await self.post(changes)
        if self.pending is None or spmg in ("Stop", "Pause"):
            await self.post({"DMOV": 1} if self.pending is None else {})
            waiters, self.waiters = self.waiters, []
            for fut in waiters:
                if not fut.done():
                    fut.set_result(None)

    async def stop(self) -> None:
        """STOP = 1, or SPMG Stop/Pause: S00=8 at once; targets not yet sent are dropped."""
        self.stop_gen += 1
        self.stopped = True
        if self.values["SPMG"] != "Pause":
            self.pending = None
        await self.act((0, 8), why="stop")
        if self._runner is None and self.pending is None:
            # Nothing of ours was moving: a record at rest only sends the stop (do_work()).
            self.stopped = False
        await self.post({"STOP": 0})

    async def spmg(self, value: str) -> None:
        await self.post({"SPMG": value, "LSPG": value})
        if value in ("Stop", "Pause"):
            await self.stop()
            if value == "Stop" and self._runner is None:
                await self._sync()
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
                               why="set the dial position")
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
        await self.act((23 if high else 24, drive_side * inversion), why=f"set {field}")
        await self.poll(slow=True)


__all__ = ["AxisRecord", "IDLE_PERIOD", "MOVING_PERIOD", "max_transfers_per_second"]
