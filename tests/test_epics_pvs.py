"""The record's channels in one process, no network: what a monitor's client finds
when it reacts to that monitor (issue 33).

ophyd's ``EpicsMotor`` answers an HLM or LLM monitor with a DBR_CTRL get of VAL
(``on_limit_changed``: ``user_setpoint._read_pv.get_ctrlvars()``) and keeps what it got;
``m.limits`` once read the old LLM for ever when that get arrived between LLM's monitor
and VAL's new control limits. In an IOC the limits are in place before the monitor
(``get_control_double()`` reads the record's fields), so the channels must be too.
"""
from __future__ import annotations

import asyncio
from types import SimpleNamespace
from typing import Any, Dict, List

import pytest

from tests.epics_harness import NO_SERVER

pytestmark = pytest.mark.skipif(NO_SERVER is not None, reason=NO_SERVER or "")


def channels() -> Any:
    from tcp_bridge.epics.axis import AxisRecord
    from tcp_bridge.epics.pvs import RecordChannels

    axis = SimpleNamespace(position_factor=1000.0, bus="can0", node_id=3)
    engine = SimpleNamespace(table=SimpleNamespace(axes={3: axis}))
    return RecordChannels(AxisRecord(engine, 3), "TST:m3")


def watch(ch: Any, field: str, seen: List[Dict[str, float]]) -> None:
    """Record VAL's and DVAL's control limits at the moment ``field``'s value is written
    (its monitor is queued then)."""
    channel = ch.by_field[field]
    write = channel.write

    async def spy(value: Any, **kw: Any) -> Any:
        val, dval = ch.by_field["VAL"], ch.by_field["DVAL"]
        seen.append(dict(lo=val.lower_ctrl_limit, hi=val.upper_ctrl_limit,
                         dlo=dval.lower_ctrl_limit, dhi=dval.upper_ctrl_limit))
        return await write(value, **kw)

    channel.write = spy


@pytest.mark.parametrize("changes", [
    {"HLM": 6.0, "DHLM": 6.0},
    {"LLM": -6.0, "DLLM": -6.0},
    {"HLM": 6.0, "LLM": -6.0, "DHLM": 6.0, "DLLM": -6.0},
])
def test_val_s_control_limits_are_in_place_before_a_limit_s_monitor(
        changes: Dict[str, float]) -> None:
    ch = channels()
    asyncio.run(ch.post({"HLM": 2.0, "LLM": -2.0, "DHLM": 2.0, "DLLM": -2.0}))
    seen: List[Dict[str, float]] = []
    for field in changes:
        watch(ch, field, seen)
    asyncio.run(ch.post(changes))
    expected = dict(lo=changes.get("LLM", -2.0), hi=changes.get("HLM", 2.0),
                    dlo=changes.get("DLLM", -2.0), dhi=changes.get("DHLM", 2.0))
    assert seen == [expected] * len(changes)


def test_units_and_precision_are_in_place_before_egu_s_monitor() -> None:
    ch = channels()
    seen: List[Any] = []
    egu = ch.by_field["EGU"]
    write = egu.write

    async def spy(value: Any, **kw: Any) -> Any:
        seen.append((ch.by_field["VAL"].units, ch.by_field["VELO"].units,
                     ch.by_field["VAL"].precision))
        return await write(value, **kw)

    egu.write = spy
    asyncio.run(ch.post({"EGU": "deg", "PREC": 2}))
    assert seen == [("deg", "deg/sec", 2)]


def test_a_put_s_completion_waits_for_events_still_in_the_context_s_queue() -> None:
    """caproto's context queue holds a published event until its loop hands it to each
    circuit; the completion must wait for that too (pyepics ``Motor.move`` read LVIO 0
    for a refused move under load when only the circuits' queues were looked at)."""
    ch = channels()

    async def scenario() -> List[str]:
        order: List[str] = []
        circuit = SimpleNamespace(subscription_queue=asyncio.Queue())
        ch.context = SimpleNamespace(subscription_queue=asyncio.Queue(), circuits=[circuit])
        ch.context.subscription_queue.put_nowait("LVIO = 1")

        async def context_loop() -> None:  # a loaded loop: the event waits a while
            for _ in range(20):
                await asyncio.sleep(0.001)
            circuit.subscription_queue.put_nowait(ch.context.subscription_queue.get_nowait())
            await asyncio.sleep(0.005)
            order.append(circuit.subscription_queue.get_nowait())  # sent

        task = asyncio.ensure_future(context_loop())
        await ch.drain()
        order.append("completion")
        await task
        return order

    assert asyncio.run(scenario()) == ["LVIO = 1", "completion"]
