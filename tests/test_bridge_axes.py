"""Tests of tcp_bridge.tables.axes (the axis table, spec section 3) and tcp_bridge.tables.parameters.

Expected values are worked out by hand from spec 3 and 3.6 in the comments.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from importlib import resources
from pathlib import Path
from typing import Any, Dict

import pytest

from tcp_bridge.tables.axes import (DEFAULTS, AxisTable, BusOffset, ConfigError, DeviceCode,
                             simulated_increments_per_revolution, simulated_table)
from tcp_bridge.tables.parameters import ParameterStore, write_atomically

# An EPOS4 (device 5) takes rpm: rpm = user/s * factor * 60 / IPR. With IPR 60 and
# factor 1000 a drive value is user * 1000, the hand-worked values of spec 3.6.
IPR = 60

EXAMPLE = Path(str(resources.files("tcp_bridge") / "example_axes.toml"))


def table(**extra: Any) -> Dict[str, Any]:
    data: Dict[str, Any] = {
        "bus": {"can1": {"backend": "instant"}, "can2": {"backend": "instant"}},
        "axis": [
            {"device": 5, "node_id": 1, "position_factor": 1000, "increments_per_revolution": IPR,
             "parameters": {"velocity": 2.5, "offset": 1.25, "26": 50}},
            {"addr": 2, "device": "nanotec", "node_id": 3, "bus_offset": 100000},
        ],
    }
    data.update(extra)
    return data


def test_example_file_loads_and_is_documented() -> None:
    t = AxisTable.load(EXAMPLE)
    assert sorted(t.axes) == [1, 2, 3]
    assert t.axes[1].device is DeviceCode.C_DC_MAXON_EPOS4
    assert t.axes[3].bus_offset is BusOffset.CAN2 and t.axes[3].bus == "can2"
    assert t.axes[3].parameters == {22: -1, 25: 12.5, 40: 35}
    assert t.buses["can1"].backend == "canopen" and t.buses["can2"].backend == "epos"
    assert t.settings.state_file == EXAMPLE.parent / "tcp-bridge-state.json"
    text = EXAMPLE.read_text()
    for name in ("velocity", "slave_direction", "sdo_index", "C_DC_MAXON_EPOS4", "100000"):
        assert name in text


def test_the_example_table_says_it_is_for_real_hardware_and_names_the_simulator_s_resolution() -> None:
    """Copied to the simulator, its 2048 inc/rev get "units mismatch" from check: its
    opening comment says so before anyone copies it, with the simulator's own figure."""
    head = EXAMPLE.read_text().split("\n[")[0]
    assert "for real hardware" in head
    assert f"{simulated_increments_per_revolution()} increments per" in head
    assert "units mismatch" in head and "example_heartbeat_axes.toml" in head
    ipr = {a.increments_per_revolution for a in AxisTable.load(EXAMPLE).axes.values()
           if a.device is DeviceCode.C_DC_MAXON_EPOS4}
    assert ipr == {2048}, "the comment's figure is the table's"


def test_the_heartbeat_example_is_a_table_for_the_simulator() -> None:
    """tcp_bridge/example_heartbeat_axes.toml (docs/simulator.md runs it against
    epos-link sim in tests/test_bridge_heartbeat_e2e.py): a canopen bus over socketcand
    with a heartbeat, and the simulator's resolution, so check finds no units mismatch."""
    t = AxisTable.load(EXAMPLE.parent / "example_heartbeat_axes.toml")
    bus = t.buses["can1"]
    assert bus.backend == "canopen" and bus.options["interface"] == "socketcand"
    assert bus.options["heartbeat_ms"] == 100
    assert [a.increments_per_revolution for a in t.axes.values()] == [simulated_increments_per_revolution()]
    assert t.settings.state_file is None  # the scenario leaves no file behind


def test_epos4_device_code_is_5() -> None:
    # Spec 3.5 stops at 4 (C_DC_COBLEY_CAN); 5 is this bridge's addition.
    assert [int(c) for c in DeviceCode] == [0, 1, 2, 3, 4, 5]
    assert DeviceCode.C_DC_MAXON_EPOS4 == 5


def test_addr_defaults_to_position_and_parameters_by_name_or_number() -> None:
    t = AxisTable.from_mapping(table())
    a = t.axes[1]
    assert (a.addr, a.node_id, a.position_factor, a.bus) == (1, 1, 1000, "can1")
    assert a.parameters == {5: 2.5, 25: 1.25, 26: 50}
    assert t.axes[2].device is DeviceCode.C_DC_NANOTEC


@pytest.mark.parametrize("change,message", [
    ({"axis": [{"addr": 61, "node_id": 1}]}, "1..60"),
    ({"axis": [{"node_id": 1}, {"addr": 1, "node_id": 2}]}, "twice"),
    ({"axis": [{"node_id": 128}]}, "1..127"),
    ({"axis": [{"node_id": 0}]}, "internal"),
    ({"axis": [{"node_id": 1}, {"node_id": 1}]}, "share node"),
    ({"axis": [{"node_id": 1, "bus_offset": 1000000}]}, "no [bus.ethercat]"),
    ({"axis": [{"node_id": 1, "bus_offset": 5}]}, "BusOffset"),
    ({"axis": [{"node_id": 1, "device": 9}]}, "DeviceCode"),
    ({"axis": [{"node_id": 1, "device": "acme"}]}, "acme"),
    ({"axis": [{"node_id": 1, "position_factor": 0}]}, "position_factor"),
    ({"axis": [{"node_id": 1, "colour": "red"}]}, "colour"),
    ({"axis": [{"node_id": 1, "parameters": {"speed": 1}}]}, "speed"),
    ({"axis": [{"node_id": 1, "parameters": {"axis_inversion": 2}}]}, "axis_inversion"),
    ({"axis": [{"node_id": 1, "parameters": {"velocity": "fast"}}]}, "number"),
    ({"axis": [{"node_id": 1, "position_factor": 1000, "parameters": {"offset": 3e6}}]},
     "INTEGER32"),
    ({"axis": [{"node_id": 1, "parameters": {"slave_axis": 1}}]}, "slave"),
    ({"axis": [{"node_id": 1}, {"node_id": 2, "internal": True}]}, "spec 3.2"),
    ({"bridge": {"ack_timeout": 0}}, "ack_timeout"),
    ({"bridge": {"colour": 1}}, "colour"),
    ({"bus": {"can3": {"backend": "instant"}}}, "can3"),
    ({"bus": {"can1": {"interface": "virtual"}}}, "backend"),
    ({"extra": 1}, "extra"),
    # issue 10: an EPOS4 takes rpm, which needs the encoder's resolution
    ({"axis": [{"node_id": 1, "device": 5}]}, "increments_per_revolution: device 5"),
    ({"axis": [{"node_id": 1, "device": 5, "increments_per_revolution": 0}]},
     "increments_per_revolution: must be a positive integer"),
])
def test_invalid_tables_are_refused_with_a_reason(change: Dict[str, Any], message: str) -> None:
    with pytest.raises(ConfigError, match=message.replace("[", r"\[").replace(".", r"\.")):
        AxisTable.from_mapping(table(**change))


def test_bad_toml_and_missing_file(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("[[axis]\n")
    with pytest.raises(ConfigError, match="bad.toml"):
        AxisTable.load(bad)
    with pytest.raises(ConfigError, match="cannot read"):
        AxisTable.load(tmp_path / "missing.toml")


def test_internal_axes_first_and_node_zero() -> None:
    # Spec 3 example: AxAddr 1 and 2 internal with node 0, then drives.
    t = AxisTable.from_mapping(table(axis=[
        {"internal": True}, {"internal": True}, {"device": 2, "node_id": 5}]))
    assert [a.addr for a in t.internal_axes] == [1, 2]
    assert not t.axes[1].has_node and t.axes[3].has_node


def test_simulated_table() -> None:
    t = simulated_table(3)
    assert [(a.addr, a.node_id, a.position_factor, a.device) for a in t.axes.values()] == [
        (1, 1, 1000, DeviceCode.C_DC_MAXON_EPOS4), (2, 2, 1000, DeviceCode.C_DC_MAXON_EPOS4),
        (3, 3, 1000, DeviceCode.C_DC_MAXON_EPOS4)]
    assert t.buses["can1"].backend == "sim"
    # the simulated EPOS4's main sensor resolution (3000h/05h of its EDS)
    assert {a.increments_per_revolution for a in t.axes.values()} == {
        simulated_increments_per_revolution()}
    with pytest.raises(ConfigError):
        simulated_table(61)


def test_device_5_needs_increments_per_revolution_from_the_command_line(tmp_path: Path) -> None:
    path = tmp_path / "axes.toml"
    path.write_text('[bus.can1]\nbackend = "instant"\n[[axis]]\ndevice = 5\nnode_id = 1\n')
    result = subprocess.run([sys.executable, "-c", "import sys; from tcp_bridge.cli import main; "
                             "sys.exit(main(sys.argv[1:]))", "serve", "--config", str(path)],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 2
    assert "Traceback" not in result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "[[axis]] AxAddr 1" in lines[0] and "increments_per_revolution" in lines[0]


# --- the parameter array ----------------------------------------------------------


def test_defaults_and_configured_values_in_stored_form() -> None:
    store = ParameterStore(AxisTable.from_mapping(table()))
    # velocity 2.5 mm/s at factor 1000 is stored as 2500 (spec 4 footnote)
    assert store.get(1, 5) == 2500 and store.user(1, 5) == 2.5
    assert store.get(1, 25) == 1250  # offset 1.25 -> 1250
    assert store.get(1, 26) == 50000
    assert store.get(1, 19) == 5  # device code from the axis
    assert store.get(1, 22) == 1 and store.get(1, 31) == 3 and store.get(1, 80) == 0x60410002
    assert store.get(1, 2) is None and DEFAULTS[2] is None  # the drive's own value stands
    s = store.scaling(1)
    assert (s.factor, s.inversion, s.offset) == (1000, 1, 1.25)
    assert store.device(2) is DeviceCode.C_DC_NANOTEC


def test_state_file_persists_s_commands_only(tmp_path: Path) -> None:
    path = tmp_path / "state" / "bridge.json"
    t = AxisTable.from_mapping(table())
    store = ParameterStore(t, path)
    assert not path.exists()  # nothing set yet
    store.set_user(1, 22, -1)
    store.set_user(1, 41, 0.5)  # homing velocity 0.5 mm/s -> 500
    assert store.flush(5)  # written in the background
    data = json.loads(path.read_text())
    assert data["axes"] == {"1": {"position_factor": 1000, "parameters": {"22": -1, "41": 500}}}
    again = ParameterStore(t, path)
    assert again.get(1, 22) == -1 and again.get(1, 41) == 500
    assert again.get(1, 5) == 2500  # from the table, not the state file
    assert again.scaling(1).inversion == -1
    assert [p.name for p in path.parent.iterdir()] == ["bridge.json"]  # no temporary left


def test_state_file_of_another_factor_is_ignored(tmp_path: Path) -> None:
    path = tmp_path / "s.json"
    first = ParameterStore(AxisTable.from_mapping(table()), path)
    first.set_user(1, 25, 2.0)
    first.close()
    changed = table()
    changed["axis"][0]["position_factor"] = 100
    store = ParameterStore(AxisTable.from_mapping(changed), path)
    assert store.get(1, 25) == 125  # 1.25 at factor 100, the stored 2000 is not reused


@pytest.mark.parametrize("content", ["{", "[]", '{"format": "x"}',
                                     '{"format": "tcp-bridge-state", "version": 1, '
                                     '"axes": {"1": {"position_factor": 1000, '
                                     '"parameters": {"5": "fast"}}}}'])
def test_damaged_state_file_is_refused(tmp_path: Path, content: str) -> None:
    path = tmp_path / "s.json"
    path.write_text(content)
    with pytest.raises(ConfigError, match="damaged"):
        ParameterStore(AxisTable.from_mapping(table()), path)


def state(parameters: str, factor: int = 1000) -> str:
    return ('{"format": "tcp-bridge-state", "version": 1, "axes": {"1": {"position_factor": '
            f'{factor}, "parameters": {{{parameters}}}}}}}}}')


@pytest.mark.parametrize("content,why", [
    (b"\xff", "not UTF-8 text: byte 0xFF at offset 0"),
    (b'{"format": "tcp-bridge-state"\xe9}', "not UTF-8 text: byte 0xE9 at offset 29"),
    # Issue 24: a value is checked as in an S command; 23 (limit +) is scaled, INTEGER32.
    (state('"23": 100000000000000000000000000000').encode(), "is outside INTEGER32"),
    (state('"23": 1e29').encode(), "bad entry 23=1e+29"),  # a number, not an integer
    (state('"22": 5').encode(), "22=5: command 22 (Axis Inversion): 5 is not one of [-1, 1]"),
    (state('"4": true').encode(), "bad entry 4=True"),  # JSON true is not the integer 1
    (state('"31": 7').encode(), "is not one of [1, 2, 3]"),
    (state('"5": 2147483648').encode(), "is outside INTEGER32"),
])
def test_a_state_file_value_is_checked_as_in_an_s_command(tmp_path: Path, content: bytes,
                                                           why: str) -> None:
    path = tmp_path / "s.json"
    path.write_bytes(content)
    with pytest.raises(ConfigError, match="damaged") as info:
        ParameterStore(AxisTable.from_mapping(table()), path)
    assert why in str(info.value) and "\n" not in str(info.value)


def test_the_extremes_of_a_parameter_load(tmp_path: Path) -> None:
    path = tmp_path / "s.json"
    path.write_text(state('"5": 2147483647, "22": -1, "25": -2147483648, "80": 1614872578'))
    store = ParameterStore(AxisTable.from_mapping(table()), path)
    assert [store.get(1, c) for c in (5, 22, 25, 80)] == [2**31 - 1, -1, -2**31, 0x60410002]


def test_serve_with_a_state_file_that_is_not_utf8_is_one_line(tmp_path: Path) -> None:
    path = tmp_path / "s.json"
    path.write_bytes(b"\xff")
    proc = subprocess.run([sys.executable, "-m", "tcp_bridge.cli", "serve", "--simulate",
                           "--state-file", str(path), "--port", "0", "--maintenance-port", "-1"],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode != 0 and "Traceback" not in proc.stderr, proc.stderr
    assert proc.stderr.strip().splitlines() == [
        f"tcp-bridge: state file {path} is damaged (not UTF-8 text: byte 0xFF at offset 0); "
        "move it away to start from the axis table"]


def test_atomic_write_keeps_old_content_on_failure(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "f.json"
    write_atomically(path, "old")

    def broken_replace(src: str, dst: str) -> None:
        raise OSError("disk full")
    monkeypatch.setattr(os, "replace", broken_replace)
    with pytest.raises(OSError):
        write_atomically(path, "new")
    assert path.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["f.json"]


def test_concurrent_sets_leave_the_newest_state(tmp_path: Path) -> None:
    import threading

    path = tmp_path / "s.json"
    t = AxisTable.from_mapping(table())
    store = ParameterStore(t, path)

    def writer(cmd: int) -> None:
        for i in range(50):
            store.set(1, cmd, i)

    threads = [threading.Thread(target=writer, args=(c,)) for c in (20, 21, 54)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    store.close()
    again = ParameterStore(t, path)
    assert [again.get(1, c) for c in (20, 21, 54)] == [49, 49, 49]


def test_failed_state_file_write_keeps_the_value_and_logs(tmp_path: Path,
                                                          caplog: pytest.LogCaptureFixture) -> None:
    blocker = tmp_path / "gone"
    store = ParameterStore(AxisTable.from_mapping(table()), blocker / "s.json")
    blocker.rmdir()  # made by the start-up check (issue 12) ...
    blocker.write_text("x")  # ... replaced after start: the directory cannot be created
    with caplog.at_level("ERROR", logger="tcp_bridge.tables.parameters"):
        store.set_user(1, 22, -1)  # does not raise: the change took effect
        assert store.flush(5)
    assert store.get(1, 22) == -1
    assert "NOT persisted" in caplog.text and str(blocker / "s.json") in caplog.text


def test_state_file_is_written_in_the_background_newest_snapshot_wins(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import threading

    import tcp_bridge.tables.parameters as parameters

    writes = []
    real = parameters.write_atomically
    disk = threading.Event()  # a disk that is stuck until the test lets it go
    gave_up = []

    def slow_disk(path: Path, text: str) -> None:
        if not disk.wait(30):
            gave_up.append(True)
        writes.append(json.loads(text))
        real(path, text)
    monkeypatch.setattr(parameters, "write_atomically", slow_disk)
    path = tmp_path / "s.json"
    store = ParameterStore(AxisTable.from_mapping(table()), path)
    for i in range(20):
        store.set(1, 54, i)  # returns at once: the caller is a bus worker
    # Every set() returned while the first write was still stuck on the disk
    # (had one waited for it, the loop would have ended only after 30 s).
    assert gave_up == [] and writes == []
    disk.set()
    store.close()  # flushes
    assert len(writes) <= 2  # the stuck one and the newest: coalesced, not 20 writes
    assert writes[-1]["axes"]["1"]["parameters"] == {"54": 19}
    assert gave_up == []
    assert ParameterStore(AxisTable.from_mapping(table()), path).get(1, 54) == 19
