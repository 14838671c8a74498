"""Issue 30 finding 2 on EtherCAT: a line is one motion. Two simulated EPOS4 slaves on a
veth pair are the internal axes of a line (tests/test_bridge_ethercat_csp.py's
set-up: the bridge in a subprocess, the slaves in this process); mid-line, slave 2
faults (8611h following error, injected in its drive model). The bridge reads the
slaves' statuswords from the inputs of every cycle, so slave 1 ramps down on the line
at 28 at once instead of running on to its target; R86 of axis 2 is 0 and the log
names it. Needs root, iproute2 and pysoem (each missing piece skips, saying which).
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Tuple

import pytest

from epos_link.cia402 import State
from tests.helpers import wait_until
from tests.test_bridge_ethercat_csp import (FACTOR, WHY_NOT, Sampler, ask, bridge,  # noqa: F401
                                            ok, server)

pytestmark = pytest.mark.skipif(bool(WHY_NOT), reason=WHY_NOT or "runs")

DISTANCE = 100  # mm: 5 s at 20 mm/s


def test_a_slave_that_faults_mid_line_stops_the_other_on_the_line(
        server: Tuple[object, str], bridge, tmp_path: Path) -> None:  # noqa: F811
    sim = server[0]
    sock, _ = bridge
    ok(sock, "1S04=1", "2S04=1", f"1S02={DISTANCE}", f"2S02={DISTANCE}")
    sampler = Sampler(sim)
    start = sampler.now()
    ok(sock, "1S90=1")
    wait_until(lambda: sampler.now()[1] - start[1] > 10 * FACTOR, 60, "never got going")
    at_fault = sampler.now()
    faulty = sim.drives[1]  # type: ignore[attr-defined]
    with faulty.lock:
        faulty.drive.inject_fault("following_error")
    wait_until(lambda: ask(sock, "1R82")[1] == "1", 60, "the line never ended")
    time.sleep(0.1)
    seen = sampler.close()
    rest = seen[-1]
    assert rest[1] - start[1] < (DISTANCE - 50) * FACTOR, "slave 1 ran on to its target"
    travelled = rest[1] - at_fault[1]
    assert 1.5 * FACTOR < travelled < 15 * FACTOR, travelled  # its stop ramp at 28, no step
    assert rest[3] is State.OPERATION_ENABLED and rest[4] is not State.OPERATION_ENABLED
    assert ask(sock, "1R86")[1] == "1" and ask(sock, "2R86")[1] == "0"
    log = (tmp_path / "bridge.log").read_text()
    assert "axis 2 left its cyclic move (FAULT" in log, log[-3000:]
    ok(sock, "2S17=1")  # fault reset: the module's slaves are left as they were found
