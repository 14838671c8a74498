"""The arithmetic of a motor record, pure: coordinates, limits, and a status sample
turned into the record's live fields.

Everything here is what epics-modules/motor ``motorApp/MotorSrc/motorRecord.cc``
(R6.9 and later) computes, cited by function:

* **Coordinates** (``do_work()``'s header): user = dial * DIR + OFF, dial = raw * MRES.
  The bridge's *dial* is the axis's PSI user position: what ``R12`` answers, with the
  PSI offset (25) and inversion (22) applied; MRES is one drive increment,
  1 / position_factor (spec 3.6). So an EPICS client and a PSI client read the same
  number when OFF = 0 and DIR = Pos.
* **User limits** from dial limits (``set_userlimits()``), and back (``special()``,
  cases HLM/LLM): with DIR = Neg the high user limit is the negated low dial limit.
* **Limit violation** (``do_work()``, "Check for soft-travel limit violation"): none
  when DHLM = DLLM = 0; a target beyond DHLM/DLLM violates, unless it moves an axis
  that is already outside back towards the valid range.
* **Too small to move** (``do_work()``, ``too_small``): the raw target equals the raw
  readback (NINT), so no move is sent; DMOV still blinks.
* **New target monitor** (``process()``, NTM): a new target behind the running move.
* **MSTA** bits (``motor.h``, ``msta_field``) and the alarm (``alarm_sub()``:
  CNTRL_COMM_ERR gives COMM/INVALID, SLIP_STALL or PROBLEM gives STATE/MAJOR).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Dict, Optional, Tuple

from epos_link.cia402 import State, state_from_statusword

from . import fields as F
from ..cia402_words import Sw

# Alarm status/severity (EPICS base menuAlarmStat / menuAlarmSevr indices).
STAT_STATE, STAT_COMM = F.STAT_MENU.index("STATE"), F.STAT_MENU.index("COMM")
SEVR_NONE, SEVR_MAJOR, SEVR_INVALID = 0, 2, 3

# Spec 4.b bits of R11 (user frame): positive and negative limit switch.
ERR_POSITIVE_SWITCH, ERR_NEGATIVE_SWITCH = 1 << 6, 1 << 7
_ENABLED = frozenset({State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE})


def nint(x: float) -> int:
    """motor.h ``NINT``: nearest integer, halves away from zero."""
    return int(x + 0.5) if x > 0 else int(x - 0.5)


@dataclass(frozen=True)
class Frame:
    """The record's calibration: OFF, DIR (+1 Pos, -1 Neg) and MRES."""

    off: float = 0.0
    dir: int = 1
    mres: float = 1.0

    def user(self, dial: float) -> float:
        return dial * self.dir + self.off

    def dial(self, user: float) -> float:
        return (user - self.off) / self.dir

    def raw(self, dial: float) -> int:
        return nint(dial / self.mres)

    def user_limits(self, dhlm: float, dllm: float) -> Tuple[float, float]:
        """(HLM, LLM) from (DHLM, DLLM): ``set_userlimits()``."""
        if self.dir == 1:
            return dhlm + self.off, dllm + self.off
        return -dllm + self.off, -dhlm + self.off

    def dial_limit_of_user(self, which: str, value: float) -> Tuple[str, float]:
        """A put to HLM or LLM as the dial limit it sets: ``special()`` cases HLM/LLM."""
        if self.dir == 1:
            return ("DHLM" if which == "HLM" else "DLLM"), value - self.off
        return ("DLLM" if which == "HLM" else "DHLM"), -value + self.off


def limits_off(dhlm: float, dllm: float) -> bool:
    """DHLM = DLLM = 0: the record has no soft limits."""
    return dhlm == dllm == 0.0


def violates(dval: float, ldvl: float, dhlm: float, dllm: float) -> bool:
    """LVIO for a move from dial ``ldvl`` to ``dval`` (``do_work()``)."""
    if limits_off(dhlm, dllm):
        return False
    if (dval > dhlm and dval < ldvl) or (dval < dllm and dval > ldvl):
        return False  # out of range, but moving back towards it
    return dval > dhlm or dval < dllm


def too_small(dval: float, drbv: float, mres: float) -> bool:
    """No move: the raw target is the raw readback (``do_work()``, ``too_small``)."""
    return nint(dval / mres) == nint(drbv / mres)


def runs_away(target: float, drbv: float, cdir: int, *, mres: float, ntmf: float,
              bdst: float, rdbd: float) -> bool:
    """The new target monitor (``process()``, NTM = YES): the axis, commanded in
    direction ``cdir`` (1 positive), runs away from dial ``target``: the sign of RDIF
    (target - readback, in steps) is not CDIR, by more than NTMF x (|BDST| + RDBD)."""
    sign_rdif = 0 if nint((target - drbv) / mres) < 0 else 1
    return sign_rdif != cdir and abs(target - drbv) > ntmf * (abs(bdst) + rdbd)


@dataclass(frozen=True)
class Sample:
    """One poll of an axis, as the PSI reads answered (None: not read or failed)."""

    statusword: Optional[int] = None  # R10
    position: Optional[float] = None  # R12, the dial readback
    velocity: Optional[float] = None  # R14
    reached: Optional[int] = None  # R82
    switch: Optional[int] = None  # R83
    errors: Optional[int] = None  # R11 (spec 4.b, user frame)
    failure: Optional[str] = None  # why a read failed (the NAK's reason)
    silent: bool = False  # the bus or node is silent (no answer at all)

    @property
    def state(self) -> Optional[State]:
        return None if self.statusword is None else state_from_statusword(self.statusword)

    @property
    def enabled(self) -> bool:
        return self.state in _ENABLED

    @property
    def fault(self) -> bool:
        return self.statusword is not None and bool(self.statusword & Sw.FAULT)

    @property
    def moving(self) -> bool:
        """The drive runs a motion: enabled and not "target reached" (R82), or turning."""
        if self.failure is not None:
            return False
        if self.enabled and self.reached == 0 and not self.homing_failed:
            return True
        return False

    @property
    def homing_failed(self) -> bool:
        """Statusword bits 13 and 10: homing error at standstill (CiA 402-2 6.6); R82
        reads 0 then, but the axis is at rest."""
        sw = self.statusword or 0
        return bool(sw & Sw.OP_MODE_13) and bool(sw & Sw.TARGET_REACHED)


def msta(sample: Sample, *, direction: int, homed: bool, problem: bool, hls_raw: bool,
         lls_raw: bool) -> int:
    """The MSTA word (motor.h ``msta_field``) of a sample."""
    bits = F.MSTA_GAIN_SUPPORT | F.MSTA_PRESENT  # a closed-loop servo with its encoder
    if direction > 0:
        bits |= F.MSTA_DIRECTION
    if sample.moving:
        bits |= F.MSTA_MOVING
    else:
        bits |= F.MSTA_DONE
    if hls_raw:
        bits |= F.MSTA_PLUS_LS
    if lls_raw:
        bits |= F.MSTA_MINUS_LS
    if sample.enabled:
        bits |= F.MSTA_POSITION
    if sample.failure is not None:
        bits |= F.MSTA_COMM_ERR
    if problem or sample.fault:
        bits |= F.MSTA_PROBLEM
    if homed:
        bits |= F.MSTA_HOMED
    return bits


def alarm(sample: Sample, problem: Optional[str]) -> Tuple[int, int]:
    """(STAT, SEVR) as ``alarm_sub()`` derives them from MSTA."""
    if sample.failure is not None:
        return STAT_COMM, SEVR_INVALID
    if sample.fault or problem:
        return STAT_STATE, SEVR_MAJOR
    return 0, SEVR_NONE


def switches(sample: Sample) -> Tuple[bool, bool]:
    """(raw high, raw low) limit switch: R83 says one is hit, R11 which (user frame)."""
    if not sample.switch or sample.errors is None:
        return False, False
    return bool(sample.errors & ERR_POSITIVE_SWITCH), bool(sample.errors & ERR_NEGATIVE_SWITCH)


def live_fields(sample: Sample, frame: Frame, *, dval: float, homed: bool,
                problem: Optional[str], last_direction: int) -> Dict[str, Any]:
    """The live fields a sample gives (``process_motor_info()``), in posting order.

    Readbacks only when the sample has them: a failed poll keeps the last
    readback and raises the alarm instead, as a record whose driver stopped
    answering does.
    """
    out: Dict[str, Any] = {}
    direction = last_direction
    if sample.position is not None:
        drbv = sample.position
        out["DRBV"] = drbv
        out["RBV"] = frame.user(drbv)
        out["RRBV"] = out["RMP"] = out["REP"] = frame.raw(drbv)
        out["DIFF"] = dval - drbv
        out["RDIF"] = nint((dval - drbv) / frame.mres)
    if sample.velocity:
        direction = 1 if sample.velocity > 0 else -1
        out["TDIR"] = int(direction > 0)
    if sample.velocity is not None and math.isfinite(sample.velocity):
        out["RVEL"] = nint(sample.velocity / frame.mres)
    rhls, rlls = switches(sample)
    out["RHLS"], out["RLLS"] = int(rhls), int(rlls)
    # process_motor_info(): HLS is the raw high switch when DIR and MRES agree.
    out["HLS"], out["LLS"] = (int(rhls), int(rlls)) if frame.dir == 1 else (int(rlls), int(rhls))
    out["MSTA"] = msta(sample, direction=direction, homed=homed, problem=problem is not None,
                       hls_raw=rhls, lls_raw=rlls)
    out["MOVN"] = int(sample.moving)
    if sample.failure is None:
        out["CNEN"] = F.TORQ_MENU[int(sample.enabled)]
        out["EnableRBV"] = int(sample.enabled)
    out["Connected"] = int(not sample.silent)
    out["StatusProblem"] = int(sample.fault or problem is not None or sample.failure is not None)
    out["MsgTxt"] = message(sample, problem)
    return out


def message(sample: Sample, problem: Optional[str]) -> str:
    """The -MsgTxt text: why the record is in alarm, or empty."""
    if sample.failure is not None:
        return sample.failure
    if sample.fault:
        from ..status.rows import error_names  # pure
        names = error_names(sample.errors or 0)
        return "drive fault" + (f": {', '.join(names)}" if names else "")
    return problem or ""
