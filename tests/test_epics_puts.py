"""A put the bridge refuses, the way a user meets it (issue 33): a value the PSI table
refuses (a CAN: VMAX beyond INTEGER32 once scaled) fails the CA put with ECA_PUTFAIL
(aioca, libca, in its own process), the record's ``-MsgTxt`` says why, and the
bridge's log (at -v, as the PSI ports' CAN reasons) has one line naming the axis, the
field and the reason: no traceback. The next good put clears the message."""
from __future__ import annotations

import time
from typing import Iterator

import pytest

from tests.epics_harness import Served, no_client, run_client

REASON = no_client("aioca")
pytestmark = pytest.mark.skipif(REASON is not None, reason=REASON or "")


@pytest.fixture(scope="module")
def served() -> Iterator[Served]:
    bridge = Served(["--simulate", "--axes", "2", "-v"])
    try:
        yield bridge
    finally:
        bridge.close()


def test_a_refused_put_fails_with_eca_putfail_one_log_line_and_the_reason_in_msgtxt(
        served: Served) -> None:
    out = run_client("""
        import asyncio, json
        from aioca import DBR_CHAR_STR, CANothing, caget, caput

        async def main():
            try:
                await caput("TST:m2.VMAX", 1e15, wait=True, timeout=30)
                refused = None
            except CANothing as exc:
                refused = str(exc)
            message = str(await caget("TST:m2-MsgTxt", datatype=DBR_CHAR_STR))
            severity = str(await caget("TST:m2.SEVR", datatype=str))
            await caput("TST:m2.VMAX", 50.0, wait=True, timeout=30)
            return dict(refused=refused, message=message, severity=severity,
                        after=str(await caget("TST:m2-MsgTxt", datatype=DBR_CHAR_STR)),
                        vmax=float(await caget("TST:m2.VMAX")))
        print(json.dumps(asyncio.run(main())))
        """, served.env)
    # libca's text of ECA_PUTFAIL (EPICS base caerr.h): "Channel write request failed"
    assert out["refused"] == "TST:m2.VMAX: Channel write request failed", out
    assert "VMAX" in out["message"] and "outside INTEGER32" in out["message"], out
    assert out["severity"] == "MAJOR"
    assert out["after"] == "" and out["vmax"] == pytest.approx(50.0), out
    time.sleep(0.5)  # the log line is written before the reply; let the pipe catch up
    log = "".join(served.output)
    lines = [line for line in log.splitlines() if "refused" in line]
    assert len(lines) == 1, log
    assert "axis 2" in lines[0] and "VMAX" in lines[0] and "outside INTEGER32" in lines[0]
    assert "Traceback" not in log and "Invalid write request" not in log, log
