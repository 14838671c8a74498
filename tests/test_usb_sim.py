"""Real pyusb and libusb against simulated EPOS4 units on a umockdev USB bus.

Clients run as user programs do: a separate process under ``umockdev-wrapper``
(tests/usb_client.py), with ``EPOS_LINK_LIBUSB`` choosing the ``libusb-package``
wheel's libusb or the system's. The units are served from this process by
:class:`UsbLink`. Skipped, with the reason, where umockdev or gi is missing
(``.ci/run`` installs them when it can).

No wall-clock bounds are asserted: every wait below is a generous ceiling
(tens of seconds) on something that normally takes milliseconds.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import IO, Any, Iterator, Optional

import pytest

from epos_link.simulator.usb_link import UsbLink, unavailable_reason

REASON = unavailable_reason()
if REASON:
    pytest.skip(f"USB testbed unavailable: {REASON}", allow_module_level=True)

from epos_link.simulator.core import Epos4Simulator  # noqa: E402
from epos_link.simulator.link import LinkOptions  # noqa: E402

CLIENT = Path(__file__).with_name("usb_client.py")
ROOT = Path(__file__).resolve().parent.parent
SERIALS = ["EPOSUNITA", "EPOSUNITB"]
HOME_POSITIONS = [111, 222]  # tell the two units apart
DEVICE_TYPE = 0x00020192     # EDS 0x1000 of the simulated EPOS4
WAIT = 60.0                  # ceiling for any single step


@pytest.fixture(scope="module")
def link() -> Iterator[UsbLink]:
    sims = [Epos4Simulator(1, [2]) for _ in SERIALS]
    for sim, home in zip(sims, HOME_POSITIONS):
        sim.own.store.set(0x30B0, 0, home)
    usb = UsbLink(sims, SERIALS, LinkOptions()).start()
    yield usb
    usb.close()
    for sim in sims:
        sim.close()


def client_env(link: UsbLink, libusb: str) -> dict[str, str]:
    env = dict(os.environ, **link.environment, EPOS_LINK_LIBUSB=libusb)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
    return env


def run_client(link: UsbLink, *args: str, libusb: str = "bundled") -> list[dict[str, Any]]:
    out = subprocess.run(link.command([sys.executable, str(CLIENT), *args]), capture_output=True,
                         text=True, timeout=WAIT, env=client_env(link, libusb))
    assert out.returncode == 0, out.stdout + out.stderr
    return [json.loads(line) for line in out.stdout.splitlines()]


def run_cli(link: UsbLink, *args: str, libusb: str = "bundled") -> subprocess.CompletedProcess[str]:
    return subprocess.run(link.command([sys.executable, "-m", "epos_link", *args]),
                          capture_output=True, text=True, timeout=WAIT, env=client_env(link, libusb))


def test_lists_both_units(link: UsbLink) -> None:
    [row] = run_client(link, "list")
    assert sorted(u["serial"] for u in row["units"]) == SERIALS
    assert all(u["url"] == f"usb://?serial={u['serial']}" for u in row["units"])


@pytest.mark.parametrize("url, home", [
    (f"usb://?serial={SERIALS[1]}", HOME_POSITIONS[1]),
    (f"usb://?serial={SERIALS[0]}", HOME_POSITIONS[0]),
])
def test_serial_selects_the_unit(link: UsbLink, url: str, home: int) -> None:
    out = run_cli(link, "read", url, "0", "0x30B0", "0", "--type", "i32")
    assert out.returncode == 0, out.stderr
    assert f"i32 {home}" in out.stdout


def test_index_counts_units_in_enumeration_order(link: UsbLink) -> None:
    homes = set()
    for index in (0, 1):
        out = run_cli(link, "read", f"usb://?index={index}", "0", "0x30B0", "0", "--type", "i32")
        assert out.returncode == 0, out.stderr
        homes.update(h for h in HOME_POSITIONS if f"i32 {h}" in out.stdout)
    assert homes == set(HOME_POSITIONS)  # index 0 and 1 are the two units, in some order
    out = run_cli(link, "read", "usb://?index=2", "0", "0x30B0", "0")
    assert out.returncode == 2 and "no EPOS4 USB device" in out.stderr


@pytest.mark.parametrize("libusb", ["bundled", "system"])
def test_objects_segmented_transfers_and_an_abort(link: UsbLink, libusb: str) -> None:
    steps = {r["step"]: r for r in run_client(link, "access", f"usb://?serial={SERIALS[0]}",
                                              libusb=libusb)}
    assert steps["device_type"]["value"] == DEVICE_TYPE
    assert steps["remote_device_type"]["value"] == DEVICE_TYPE   # node 2, behind the gateway
    assert steps["name"]["value"] == steps["remote_name"]["value"] == "EPOS4"
    assert steps["downloaded"]["value"] == 1234                  # segmented write, read back
    assert steps["home_position"]["value"] == -5
    assert steps["absent"] == {"step": "absent", "error": "DeviceError", "code": 0x06020000}
    link.servers[0].device.own.store.set(0x30B0, 0, HOME_POSITIONS[0])  # type: ignore[attr-defined]


class Lines:
    """Reads a client's JSON lines in a thread, so every wait has a ceiling."""

    def __init__(self, stream: IO[str]) -> None:
        self.items: list[dict[str, Any]] = []
        self._cond = threading.Condition()
        threading.Thread(target=self._run, args=(stream,), daemon=True).start()

    def _run(self, stream: IO[str]) -> None:
        for line in stream:
            with self._cond:
                self.items.append(json.loads(line))
                self._cond.notify_all()

    def wait_for(self, predicate: Any, what: str) -> dict[str, Any]:
        deadline = time.monotonic() + WAIT
        with self._cond:
            while True:
                for item in self.items:
                    if predicate(item):
                        return item
                left = deadline - time.monotonic()
                assert left > 0, f"no {what} within {WAIT} s; got {self.items[-5:]}"
                self._cond.wait(left)

    def count(self, predicate: Any) -> int:
        with self._cond:
            return sum(1 for item in self.items if predicate(item))


def start_client(link: UsbLink, *args: str, libusb: str) -> tuple[subprocess.Popen[str], Lines]:
    proc = subprocess.Popen(link.command([sys.executable, str(CLIENT), *args]), text=True,
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=client_env(link, libusb))
    assert proc.stdout is not None
    return proc, Lines(proc.stdout)


def finish(proc: subprocess.Popen[str]) -> None:
    assert proc.stdin is not None
    proc.stdin.close()
    try:
        assert proc.wait(WAIT) == 0
    finally:
        if proc.poll() is None:
            proc.kill()


def send_line(proc: subprocess.Popen[str]) -> None:
    assert proc.stdin is not None
    proc.stdin.write("\n")
    proc.stdin.flush()


def test_a_timed_out_read_discards_its_urb_and_the_late_answer_never_slides(link: UsbLink) -> None:
    server = link.servers[0]
    discards = link.stats()["counts"].get("DISCARDURB", 0)
    proc, lines = start_client(link, "late", f"usb://?serial={SERIALS[0]}", libusb="bundled")
    try:
        lines.wait_for(lambda r: r.get("step") == "ready", "ready")
        server.options.delay = 0.5                   # answers now come after the 50 ms timeout
        send_line(proc)
        timeout = lines.wait_for(lambda r: r.get("step") == "timeout", "timeout")
        assert timeout["error"] == "EposTimeoutError"
        lines.wait_for(lambda r: r.get("step") == "timed_out", "timed_out")
        server.options.delay = 0.0
        send_line(proc)
        finish(proc)
    finally:
        server.options.delay = 0.0
        if proc.poll() is None:
            proc.kill()
    after = [r for r in lines.items if r.get("step") == "after"]
    assert len(after) == 3 and all(r["ok"] for r in after), after
    assert link.stats()["counts"].get("DISCARDURB", 0) > discards  # libusb gave the IN URB up


def test_unplug_during_a_poll_loop_gives_typed_errors_then_the_same_client_reads_again(
        link: UsbLink) -> None:
    """Debian's libusb hears the testbed's hotplug events (the wheel's does not)."""
    proc, lines = start_client(link, "poll", f"usb://?serial={SERIALS[0]}", libusb="system")
    try:
        ok = lambda r: r.get("result") == "ok"  # noqa: E731
        lines.wait_for(lambda r: lines.count(ok) >= 5, "5 good polls")
        pulled_at = len(lines.items)  # before the pull: a poll may fail before unplug() returns
        link.unplug(0)
        lines.wait_for(lambda r: r.get("result") == "error", "an error while unplugged")
        time.sleep(1.0)  # the cable stays out for a second (no bound is asserted on it)
        link.replug(0)
        replugged_at = len(lines.items)
        lines.wait_for(lambda r: lines.items.index(r) >= replugged_at and ok(r), "a read after replug")
        finish(proc)
    finally:
        if proc.poll() is None:
            proc.kill()
    results = lines.items
    assert {r["result"] for r in results} <= {"ok", "error"}, [r for r in results
                                                               if r["result"] not in ("ok", "error")]
    errors = [r for r in results if r["result"] == "error"]
    assert errors and {r["error"] for r in errors} <= {"TransportError", "EposTimeoutError"}
    assert all(ok(r) for r in results[:pulled_at]), results[:pulled_at]
    assert ok(results[-1]), results[-5:]
