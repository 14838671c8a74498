"""``tcp-bridge check``: a row per axis, a verdict each, exit status, and no writes.

The verdict rules are pure (:mod:`tcp_bridge.preflight`) and tested on readings
written by hand; the reading itself runs against the simulated EPOS4 through
the real ``epos`` path and against instant fake drives, where every SDO
download and NMT command is counted to prove that the check writes nothing.
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any, Dict, List

import pytest

from epos_link.simulator.od import load_object_dictionary
from tcp_bridge.tables.axes import AxisConfig, AxisTable, DeviceCode, simulated_table
from tcp_bridge.backends import open_backend
from tcp_bridge.check import check
from tcp_bridge.preflight import MAXON_VENDOR_ID, Reading, Verdict, as_json, judge, table
from tcp_bridge.tables.units import RPM, Scaling

EPOS4 = AxisConfig(1, DeviceCode.C_DC_MAXON_EPOS4, node_id=1, position_factor=1000,
                   increments_per_revolution=2048)
TECHNOSOFT = AxisConfig(2, DeviceCode.C_DC_TECHNOSOFT_CAN, node_id=2)


def epos4_reading(**changes: Any) -> Reading:
    """What a real EPOS4 answers (EPOS4 EDS: 1000h 00020192h, vendor 000000FBh, 60A9h rpm)."""
    values: Dict[str, Any] = dict(device_type=0x00020192, name="EPOS4", vendor_id=MAXON_VENDOR_ID,
                                  product_code=0x60500000, revision=0x01700000, serial=7,
                                  statusword=0x0240, mode=1, position=12500,
                                  velocity_unit=RPM, sensor_resolution=2048)
    values.update(changes)
    return Reading(**values)


def cli(*args: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "tcp_bridge.cli", *args], capture_output=True,
                          text=True, timeout=timeout)


# -- verdicts (pure) ------------------------------------------------------------------------


@pytest.mark.parametrize("reading, verdict, words", [
    (epos4_reading(), Verdict.FOUND, ""),
    (Reading(silent="No SDO response received"), Verdict.ABSENT, "did not answer"),
    (epos4_reading(device_type=0x00000191), Verdict.WRONG_DEVICE, "profile 401"),
    (epos4_reading(vendor_id=0x0000026C), Verdict.WRONG_DEVICE, "0x0000026C"),
    (epos4_reading(vendor_id=None, failures={"1018h/01": "abort"}), Verdict.WRONG_DEVICE,
     "vendor-ID abort"),
    (epos4_reading(statusword=None, failures={"6041h": "Code 0x06020000"}),
     Verdict.WRONG_DEVICE, "6041h"),
    (epos4_reading(statusword=0x0001), Verdict.WRONG_DEVICE, "no CiA 402 state"),
    (epos4_reading(velocity_unit=0x00B40300), Verdict.UNITS_UNKNOWN, "not rpm"),
    (epos4_reading(velocity_unit=0xF9B44700), Verdict.UNITS_UNKNOWN, "not supported"),
    (epos4_reading(velocity_unit=None, failures={"60A9h": "Code 0x06020000"}),
     Verdict.UNITS_UNKNOWN, "60A9h"),
    (epos4_reading(sensor_resolution=None, failures={"3000h/05": "Code 0x06020000"}),
     Verdict.UNITS_UNKNOWN, "3000h/05h"),
    (epos4_reading(sensor_resolution=4096), Verdict.UNITS_MISMATCH, "4096/2048"),
])
def test_verdicts_of_an_epos4_axis(reading: Reading, verdict: Verdict, words: str) -> None:
    report = judge(EPOS4, reading)
    assert report.verdict is verdict
    assert words in report.detail
    assert report.ok is (verdict is Verdict.FOUND)


def test_other_devices_are_not_judged_on_maxon_vendor_or_units() -> None:
    reading = epos4_reading(vendor_id=0x000001A3, velocity_unit=None, sensor_resolution=None)
    assert judge(TECHNOSOFT, reading).verdict is Verdict.FOUND
    assert judge(TECHNOSOFT, reading).units == "inc/s"


def test_the_row_shows_position_in_user_units_and_the_drive_units() -> None:
    report = judge(EPOS4, epos4_reading(mode=3), Scaling(1000, -1, 2.0))
    assert report.position == pytest.approx(-12.5 + 2.0)
    text = table([report])
    header, row = text.splitlines()
    assert header.split()[:3] == ["axis", "bus/node", "verdict"]
    assert row.split()[:4] == ["1", "can1/1", "found", "EPOS4"]
    assert "switch on disabled" in row and "PVM" in row and "-10.5" in row
    assert row.endswith("rpm, 2048 inc/rev")
    data = json.loads(as_json(report))
    assert (data["addr"], data["verdict"], data["ok"], data["position"]) == (1, "found", True, -10.5)
    assert data["sensor_resolution"] == 2048 and data["velocity_unit"] == "0x00B44700"


def test_a_detail_line_follows_each_axis_that_is_not_ok() -> None:
    reports = [judge(EPOS4, epos4_reading()), judge(TECHNOSOFT, Reading(silent="timeout"))]
    lines = table(reports).splitlines()
    assert len(lines) == 4 and lines[3].strip().startswith("node 2 on can1 did not answer")


def test_the_verdict_rules_are_pure() -> None:
    import tests.test_purity as purity

    purity.test_pure_module_imports_no_io("tcp_bridge.preflight")


# -- reading the simulator and fake drives ----------------------------------------------------


def test_check_simulate_prints_a_row_per_axis_and_exits_0() -> None:
    out = cli("check", "--simulate", "--axes", "3")
    assert out.returncode == 0, out.stdout + out.stderr
    rows = [line.split() for line in out.stdout.splitlines() if line[:1].isdigit()]
    assert [r[:4] for r in rows] == [[str(n), f"can1/{n}", "found", "EPOS4"] for n in (1, 2, 3)]
    # The simulator's main sensor (3000h/05h) is what --simulate configures.
    ipr = load_object_dictionary()[0x3000][5].default
    assert all(" ".join(r[-3:]) == f"rpm, {ipr} inc/rev" for r in rows)
    assert out.stderr == ""


def test_serial_numbers_of_simulated_nodes_differ() -> None:
    out = cli("check", "--simulate", "--axes", "3", "--json")
    serials = [json.loads(line)["serial"] for line in out.stdout.splitlines()]
    assert len(serials) == 3 and len(set(serials)) == 3 and None not in serials


ABSENT_AXIS_TABLE = """
[bus.can1]
backend = "epos"
url = "sim://?node_id=1&drives=2"
timeout = 0.5

[[axis]]
addr = 1
device = "technosoft_can"
node_id = 1
position_factor = 100

[[axis]]
addr = 2
device = "technosoft_can"
node_id = 2

[[axis]]
addr = 7
device = "technosoft_can"
node_id = 4
"""


def test_an_axis_on_an_absent_node_exits_1_and_is_named(tmp_path: Path) -> None:
    config = tmp_path / "axes.toml"
    config.write_text(ABSENT_AXIS_TABLE)
    out = cli("check", "--config", str(config))
    assert out.returncode == 1, out.stdout + out.stderr
    rows = {line.split()[0]: line for line in out.stdout.splitlines() if line[:1].isdigit()}
    assert set(rows) == {"1", "2", "7"}
    assert rows["1"].split()[2] == "found" and rows["2"].split()[2] == "found"
    assert rows["7"].split()[:3] == ["7", "can1/4", "absent"]
    assert "node 4 on can1 did not answer" in out.stdout
    out = cli("check", "--config", str(config), "--json")
    verdicts = {d["addr"]: d["verdict"] for d in map(json.loads, out.stdout.splitlines())}
    assert verdicts == {1: "found", 2: "found", 7: "absent"} and out.returncode == 1


def test_a_bus_that_cannot_open_is_a_row_per_axis_naming_the_url_once(tmp_path: Path) -> None:
    missing = str(tmp_path / "no-such-tty")
    config = tmp_path / "axes.toml"
    config.write_text(f'[bus.can1]\nbackend = "epos"\nurl = "{missing}"\n'
                      '[[axis]]\nnode_id = 1\n[[axis]]\nnode_id = 2\n')
    out = cli("check", "--config", str(config))
    assert out.returncode == 1
    assert [line.split()[2] for line in out.stdout.splitlines() if line[:1].isdigit()] == \
        ["no", "no"]  # "no bus"
    detail = [line for line in out.stdout.splitlines() if missing in line][0]
    assert detail.count(missing) == 1 and "No such file or directory" in detail


def test_a_silent_device_is_one_line_for_its_bus_and_no_node_is_called_absent(
        tmp_path: Path) -> None:
    """Bus can1's EPOS4 reads and never answers; bus can2 (the embedded simulator) works."""
    from tests.test_cli_scan import Listening
    from epos_link.simulator.core import Epos4Simulator
    from epos_link.simulator.link import LinkOptions, TcpLink

    sim = Epos4Simulator(1, [2])
    device = Listening(sim)
    link = TcpLink(device, LinkOptions(silent=True)).start()
    config = tmp_path / "axes.toml"
    config.write_text(f'[bus.can1]\nbackend = "epos"\nurl = "{link.url}"\n'
                      '[bus.can2]\nbackend = "sim"\n'
                      '[[axis]]\nnode_id = 1\n[[axis]]\nnode_id = 2\n'
                      '[[axis]]\nnode_id = 1\nbus_offset = 100000\n')
    try:
        out = cli("check", "--config", str(config))
        as_json = cli("check", "--config", str(config), "--json")
    finally:
        link.close()
        sim.close()
    assert out.returncode == 1, out.stdout + out.stderr
    rows = [line.split() for line in out.stdout.splitlines() if line[:1].isdigit()]
    assert [r[:4] for r in rows] == [["1", "can1/1", "device", "silent"],
                                     ["2", "can1/2", "device", "silent"],
                                     ["3", "can2/1", "found", "EPOS4"]]
    details = [line.strip() for line in out.stdout.splitlines() if line.startswith("     ")]
    assert len(details) == 1, out.stdout  # one line for the bus, not one per axis
    assert details[0].startswith(f"bus can1: the EPOS4 at {link.url} does not answer")
    assert "baud rate" in details[0] and "power" in details[0] and "absent" not in out.stdout
    verdicts = [json.loads(line)["verdict"] for line in as_json.stdout.splitlines()]
    assert verdicts == ["device silent", "device silent", "found"] and as_json.returncode == 1
    # Only the probes of the EPOS4 itself reached it (3 per run): no node was asked.
    assert device.frames <= 2 * 3


@pytest.mark.parametrize("args, words", [
    (["--config", "/nonexistent/axes.toml"], "cannot read axis table"),
    (["--simulate", "--axes", "0"], "--axes must be 1..60"),
    (["--simulate", "--axes", "x"], "is not a number of axes"),
    ([], "one of the arguments --config --simulate is required"),
])
def test_unusable_input_is_one_line_and_exit_2(args: List[str], words: str) -> None:
    out = cli("check", *args)
    assert out.returncode == 2 and words in out.stderr and "Traceback" not in out.stderr


class Counted:
    """Wraps an opener: counts what reaches the drives besides reads."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        self.monkeypatch = monkeypatch
        self.reads = 0
        self.writes: List[Any] = []
        self.backends: List[Any] = []

    def count(self, target: Any, name: str, bucket: str) -> None:
        original = getattr(target, name)

        def call(*args: Any, **kwargs: Any) -> Any:
            if bucket == "reads":
                self.reads += 1
            else:
                self.writes.append((name, args))
            return original(*args, **kwargs)
        self.monkeypatch.setattr(target, name, call)

    def __call__(self, bus: Any, axes: List[AxisConfig]) -> Any:
        backend = open_backend(bus, axes)
        self.backends.append(backend)
        sim = getattr(backend, "simulator", None)
        if sim is not None:  # the simulated EPOS4: every SDO ends in a drive's object store
            for drive in sim.drives.values():
                self.count(drive.store, "read", "reads")
                self.count(drive.store, "write", "writes")
                self.count(drive, "nmt", "writes")
            self.count(sim, "write", "writes")
            self.count(sim, "nmt", "writes")
        return backend


def test_check_writes_nothing_to_the_simulated_drives(monkeypatch: pytest.MonkeyPatch) -> None:
    opener = Counted(monkeypatch)
    reports = check(simulated_table(3), opener=opener)
    assert [r.axis.addr for r in reports] == [1, 2, 3]
    assert all(r.reading.statusword is not None for r in reports)
    assert opener.reads >= 3 * 10  # the counter sees what reaches the drives
    assert opener.writes == []


def test_check_writes_nothing_to_fake_drives_and_sends_no_nmt() -> None:
    config = AxisTable.from_mapping({
        "bus": {"can1": {"backend": "instant", "absent": [3]}},
        "axis": [{"device": 2, "node_id": n} for n in (1, 2, 3)]})
    backends: List[Any] = []

    def opener(bus: Any, axes: List[AxisConfig]) -> Any:
        backends.append(open_backend(bus, axes))
        return backends[0]
    reports = check(config, opener=opener)
    assert [r.verdict for r in reports] == [Verdict.FOUND, Verdict.FOUND, Verdict.ABSENT]
    nodes = backends[0].nodes
    assert all(kind == "upload" for node in nodes.values() for kind, *_ in node.log)
    assert sum(len(node.log) for node in nodes.values()) >= 2 * 3  # 6041h 6061h 6064h each
    assert all(node.nmt.state == "PRE-OPERATIONAL" and node.resets == 0 for node in nodes.values())
    assert backends[0].closed
