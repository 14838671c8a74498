"""Configuration mistakes end in one line naming file, table and key, and exit 2 (issue 12,
must show 4). The files are written as a user mistypes them; ``tcp-bridge serve`` reads them.
"""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Any, Dict

import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from tcp_bridge import cli
from tcp_bridge.tables.axes import AxisTable, ConfigError

GOOD_BUS = '[bus.can1]\nbackend = "instant"\n'
GOOD_AXIS = "[[axis]]\nnode_id = 1\n"

# (file text, what the one line must contain: the table and the key)
MISTAKES = {
    "axis_single_brackets": (GOOD_BUS + "[axis]\nnode_id = 1\n",
                             "[axis] is a single table; write [[axis]] (two brackets)"),
    "parameters_is_a_number": (GOOD_BUS + GOOD_AXIS + "parameters = 5\n",
                               "[[axis]] #1 (AxAddr 1): parameters must be a table, not int 5"),
    "bus_is_a_number": ("bus = 5\n" + GOOD_AXIS, "[bus] must be a table, not int 5"),
    "bus_name_is_a_string": ('[bus]\ncan1 = "sim"\n' + GOOD_AXIS,
                             "[bus.can1] must be a table, not str 'sim'"),
    "misspelt_axis_key": (GOOD_BUS + "[[axis]]\nnode = 1\n",
                          "[[axis]] #1: unknown key 'node' (did you mean 'node_id'?)"),
    "misspelt_bridge_key": ("[bridge]\nack_timout = 2.0\n" + GOOD_BUS + GOOD_AXIS,
                            "[bridge]: unknown key 'ack_timout' (did you mean 'ack_timeout'?)"),
    "misspelt_parameter": (GOOD_BUS + GOOD_AXIS + "[axis.parameters]\nvelocty = 1.0\n",
                           "parameters.velocty: unknown parameter 'velocty' (did you mean "
                           "'velocity'?)"),
    "misspelt_device": (GOOD_BUS + '[[axis]]\nnode_id = 1\ndevice = "nanotek"\n',
                        "device: 'nanotek' is not one of"),
    "misspelt_bus": ('[bus.cann1]\nbackend = "instant"\n' + GOOD_AXIS,
                     "[bus.cann1]: bus 'cann1' is not one of can1, can2, ethercat (did you "
                     "mean 'can1'?)"),
    "timeout_is_a_string": ('[bridge]\nack_timeout = "2"\n' + GOOD_BUS + GOOD_AXIS,
                            "[bridge]: ack_timeout: must be a positive number of seconds, not "
                            "str '2'"),
    "node_id_is_a_string": (GOOD_BUS + '[[axis]]\nnode_id = "1"\n',
                            "[[axis]] #1 (AxAddr 1): node_id: must be an integer, not str '1'"),
    "node_id_out_of_range": (GOOD_BUS + "[[axis]]\nnode_id = 200\n",
                             "[[axis]] AxAddr 1: node_id: 200 is not 1..127 (spec 3.4)"),
    "internal_is_a_number": (GOOD_BUS + "[[axis]]\nnode_id = 1\ninternal = 1\n",
                             "internal: must be true or false, not int 1"),
    "no_axes": (GOOD_BUS, "no axes: add an [[axis]] table for each drive"),
    "empty_file": ("", "no axes"),
    "allow_not_a_network": ('[bridge]\nallow = ["10.0.0.300/8"]\n' + GOOD_BUS + GOOD_AXIS,
                            "[bridge]: allow: '10.0.0.300/8' is not a network in CIDR notation"),
    "bus_option_of_the_wrong_type": ('[bus.can1]\nbackend = "sim"\ntimeout = "fast"\n'
                                     + GOOD_AXIS, "[bus.can1]: timeout: must be a positive "
                                     "number of seconds, not str 'fast'"),
    # Issue 24: each names its key; bitrate used to start a server (python-can's
    # virtual interface ignores it).
    "epos_timeout": ('[bus.can1]\nbackend = "epos"\nurl = "sim://"\ntimeout = "slow"\n'
                     + GOOD_AXIS, "[bus.can1]: timeout: must be a positive number of seconds"),
    "epos_baudrate": ('[bus.can1]\nbackend = "epos"\nurl = "/dev/ttyACM0"\nbaudrate = "fast"\n'
                      + GOOD_AXIS, "[bus.can1]: baudrate: must be a positive integer (bit/s), "
                      "not str 'fast'"),
    "epos_retries": ('[bus.can1]\nbackend = "epos"\nurl = "sim://"\nretries = -1\n'
                     + GOOD_AXIS, "[bus.can1]: retries: must be an integer, 0 or more, not"),
    "epos_gateway": ('[bus.can1]\nbackend = "epos"\nurl = "sim://"\ngateway_node_id = 128\n'
                     + GOOD_AXIS, "[bus.can1]: gateway_node_id: must be a node id 1..127"),
    "sim_baud": ('[bus.can1]\nbackend = "sim"\nbaud = "x"\n' + GOOD_AXIS,
                 "[bus.can1]: baud: must be a positive integer (bit/s), not str 'x'"),
    "canopen_bitrate": ('[bus.can1]\nbackend = "canopen"\ninterface = "virtual"\nchannel = "t"\n'
                        'bitrate = "fast"\n' + GOOD_AXIS,
                        "[bus.can1]: bitrate: must be a positive integer (bit/s), not str 'fast'"),
    "canopen_bitrate_float": ('[bus.can1]\nbackend = "canopen"\ninterface = "virtual"\n'
                              'bitrate = 5e5\n' + GOOD_AXIS, "[bus.can1]: bitrate: must be a"),
    "canopen_sdo_timeout": ('[bus.can1]\nbackend = "canopen"\ninterface = "virtual"\n'
                            'sdo_timeout = true\n' + GOOD_AXIS,
                            "[bus.can1]: sdo_timeout: must be a positive number of seconds, "
                            "not the boolean true"),
    # Issue 35: a lone string is not a list of networks; an unknown URL scheme is a mistake,
    # not a bus that stays silent.
    "allow_is_a_string": ('[bridge]\nallow = "10.0.0.0/8"\n' + GOOD_BUS + GOOD_AXIS,
                          "[bridge]: allow: must be a list of networks such as "
                          "[\"10.1.2.0/24\"], not str '10.0.0.0/8'"),
    "epos_url_unknown_scheme": ('[bus.can1]\nbackend = "epos"\nurl = "bogus://x"\n' + GOOD_AXIS,
                                "[bus.can1]: url: must be a device path or a URL of a known "
                                "scheme"),
    "state_file_unwritable": ('[bridge]\nstate_file = "blocker/state.json"\n' + GOOD_BUS
                              + GOOD_AXIS, "[bridge] state_file: "),
}


def run_serve(path: Path, capsys: pytest.CaptureFixture[str]) -> str:
    assert cli.main(["serve", "--config", str(path), "--port", "0",
                     "--maintenance-port", "-1"]) == 2
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err  # one line, no traceback
    return lines[0]


@pytest.mark.parametrize("name", sorted(MISTAKES))
def test_each_mistake_is_one_line_with_file_table_and_key(
        name: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    text, expected = MISTAKES[name]
    path = tmp_path / "axes.toml"
    path.write_text(text)
    (tmp_path / "blocker").write_text("a file where a directory belongs")
    line = run_serve(path, capsys)
    assert line.startswith(f"tcp-bridge: {path}: "), line  # names the file
    assert expected in line, line


def test_unwritable_state_file_is_refused_at_start_up(tmp_path: Path,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    # Running as root, permissions would not stop a write: a file where the
    # state file's directory belongs does.
    (tmp_path / "blocker").write_text("x")
    path = tmp_path / "axes.toml"
    path.write_text('[bridge]\nstate_file = "blocker/state.json"\n' + GOOD_BUS + GOOD_AXIS)
    line = run_serve(path, capsys)
    assert f"[bridge] state_file: {tmp_path / 'blocker' / 'state.json'} cannot be written" in line
    assert cli.main(["serve", "--config", str(tmp_path / "ok.toml"), "--port", "0"]) == 2
    capsys.readouterr()
    ok = tmp_path / "ok.toml"
    ok.write_text(GOOD_BUS + GOOD_AXIS)
    assert cli.main(["serve", "--config", str(ok), "--state-file",
                     str(tmp_path / "blocker" / "s.json"), "--port", "0"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == (f"tcp-bridge: --state-file {tmp_path / 'blocker' / 's.json'} cannot be "
                   f"written ({tmp_path / 'blocker'} is not a directory)")


def test_a_file_that_is_not_utf8_is_one_line_from_the_command_line(tmp_path: Path) -> None:
    path = tmp_path / "axes.toml"
    path.write_bytes(b"# Achsen f\xfcr den Br\xfcckenkran\n" + GOOD_BUS.encode() + GOOD_AXIS.encode())
    proc = subprocess.run([sys.executable, "-m", "tcp_bridge.cli", "serve", "--config", str(path)],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    assert proc.stderr == (f"tcp-bridge: {path}: not UTF-8 text (byte 0xFC at offset 10); "
                           "TOML files are UTF-8\n")


# --- any shape of document: a table, or ConfigError; never another exception -----------

scalars = st.one_of(st.none(), st.booleans(), st.integers(-10**6, 10**6),
                    st.floats(allow_nan=True), st.text(max_size=8))
keys = st.sampled_from(["addr", "device", "internal", "bus_offset", "node_id", "position_factor",
                        "parameters", "increments_per_revolution", "backend", "can1", "can2",
                        "velocity", "offset", "26", "state_file", "ack_timeout", "allow",
                        "idle_timeout", "probe_interval", "debug", "x"])
values = st.recursive(scalars, lambda inner: st.one_of(
    st.lists(inner, max_size=3), st.dictionaries(keys, inner, max_size=4)), max_leaves=12)
documents = st.fixed_dictionaries({}, optional={
    "bridge": values, "bus": values, "axis": values,
    "extra": values})


@settings(max_examples=400, suppress_health_check=[HealthCheck.too_slow])
@given(documents)
def test_any_document_gives_a_table_or_config_error(doc: Dict[str, Any]) -> None:
    try:
        AxisTable.from_mapping(doc, source="fuzz.toml")
    except ConfigError as exc:
        assert "\n" not in str(exc) and str(exc).startswith("fuzz.toml: ")


@settings(max_examples=200)
@given(st.dictionaries(keys, values, max_size=5))
def test_any_axis_row_gives_a_table_or_config_error(row: Dict[str, Any]) -> None:
    doc = {"bus": {"can1": {"backend": "instant"}}, "axis": [row]}
    try:
        AxisTable.from_mapping(doc, source="fuzz.toml")
    except ConfigError as exc:
        assert "\n" not in str(exc) and str(exc).startswith("fuzz.toml: ")


def test_bus_option_types_check_only_what_they_know() -> None:
    from tcp_bridge.tables.bus_options import option_problem

    assert option_problem("epos", "timeout", 0.5) is None and option_problem("epos", "timeout", 1) is None
    assert option_problem("epos", "timeout", float("nan")) == "must be a positive number of seconds"
    assert option_problem("canopen", "channel", 0) is None  # python-can's own (kvaser: an int)
    assert option_problem("canopen", "bitrate", 500000) is None
    assert option_problem("somebody_elses", "bitrate", "fast") is None  # an entry point's backend
