"""``epos-link read/write/scan/nmt/ports`` over socket://127.0.0.1:PORT and a pseudo-terminal,
against the scripted responder of tests/responder.py."""
from __future__ import annotations

import json
import os
import struct
import subprocess
import sys
from pathlib import Path
from typing import Any, Iterator

import pytest

from epos_link.cli import main
from tests.reference import reference_frame
from tests.responder import (
    PtyResponder,
    SocketResponder,
    answer,
    read_pair,
    read_request,
    segmented_read_pairs,
    write_pair,
)

NAME = b"EPOS4 Compact 50/8 CAN"
SCRIPT: dict[bytes, Any] = dict([
    read_pair(1, 0x6064, 0, (1000).to_bytes(4, "little")),
    read_pair(1, 0x6077, 0, (-5).to_bytes(2, "little", signed=True) + b"\xFF\xFF"),
    read_pair(2, 0x1234, 0, b"", code=0x06020000),
    write_pair(1, 0x6040, 0, b"\x0F\x00"),
    write_pair(1, 0x607A, 0, (-100).to_bytes(4, "little", signed=True)),
    *segmented_read_pairs(1, 0x1008, 0, NAME),
    # Segmented write of 9 bytes to node 0 in one segment (guide 2.1.2.2-2.1.2.3):
    (reference_frame(0x69, struct.pack("<BHBI", 0, 0x2100, 1, 9)), answer(0)),
    (reference_frame(0x6A, bytes((9, 0x02)) + b"123456789" + b"\x00"), answer(0, bytes((9, 0)))),
    # NMT start node 2 (Table 3-14)
    (reference_frame(0x70, struct.pack("<HH", 2, 1)), answer(0)),
    (read_request(3, 0x6064, 0), None),  # node 3 never answers
    read_pair(0, 0x1000, 0, struct.pack("<I", 0x00020192)),  # the EPOS4 itself answers
])


@pytest.fixture(scope="module")
def dev() -> Iterator[SocketResponder]:
    with SocketResponder(SCRIPT) as responder:
        yield responder


def cli(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_read_type_and_name_from_the_eds(dev: SocketResponder, capsys: pytest.CaptureFixture[str]) -> None:
    # 0x6064 Position actual value is INTEGER32 (CiA 402; the shipped EDS).
    code, out, err = cli(capsys, "read", dev.url, "1", "0x6064", "0")
    assert (code, out, err) == (0, "E8 03 00 00 -> i32 1000 (0x000003E8)  Position actual value\n", "")
    code, out_by_name, _ = cli(capsys, "read", dev.url, "1", "Position actual value")
    assert (code, out_by_name) == (0, out)
    code, out_snake, _ = cli(capsys, "read", dev.url, "1", "position_actual_value")
    assert (code, out_snake) == (0, out)


def test_unknown_object_is_read_as_u32_with_a_warning(capsys: pytest.CaptureFixture[str]) -> None:
    script = dict([read_pair(1, 0x5FFF, 0, (7).to_bytes(4, "little"))])
    with SocketResponder(script) as dev:
        code, out, err = cli(capsys, "read", dev.url, "1", "0x5FFF")
    assert (code, out) == (0, "07 00 00 00 -> u32 7 (0x00000007)\n")
    assert "0x5FFF/0x00 is not in the object dictionary" in err and "--type" in err


def test_unknown_name_is_a_usage_error(dev: SocketResponder, capsys: pytest.CaptureFixture[str]) -> None:
    before = dev.requests
    code, _, err = cli(capsys, "read", dev.url, "1", "Positon actual value")
    assert code == 2 and "no object named 'Positon actual value'" in err
    assert "position_actual_value" in err  # the suggestion
    assert dev.requests == before


def test_index_slash_subindex_as_watch_and_record_take_it(capsys: pytest.CaptureFixture[str]) -> None:
    """docs/epos-link.md names objects "as `read` names them (..., `0x1018/4`)": read and
    write take INDEX/SUBINDEX, and INDEX SUBINDEX as before, with the same answer."""
    script = dict([read_pair(2, 0x1018, 4, (0x5E000002).to_bytes(4, "little")),
                   write_pair(2, 0x6081, 0, (1500).to_bytes(4, "little"))])
    with SocketResponder(script) as dev:
        slash = cli(capsys, "read", dev.url, "2", "0x1018/4")
        separate = cli(capsys, "read", dev.url, "2", "0x1018", "4")
        written = cli(capsys, "write", dev.url, "2", "0x6081/0", "1500")
    assert slash == separate == (0, "02 00 00 5E -> u32 1577058306 (0x5E000002)  "
                                    "Identity object.Serial number\n", "")
    assert written == (0, "wrote u32 1500 (0x000005DC) [DC 05 00 00] to node 2 0x6081/0x00 "
                          "Profile velocity\n", "")


def test_a_subindex_given_twice_is_refused_before_sending(dev: SocketResponder,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    before = dev.requests
    code, out, err = cli(capsys, "read", dev.url, "1", "0x1018/4", "4")
    assert (code, out) == (2, "") and err.count("\n") == 1
    assert err.startswith("epos-link read: '0x1018/4' names its subindex")
    assert dev.requests == before


def test_an_unknown_name_says_how_objects_are_named(dev: SocketResponder,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = cli(capsys, "read", dev.url, "1", "no such object anywhere")
    assert code == 2 and err.count("\n") == 1
    assert err.startswith("epos-link read: no object named 'no such object anywhere'")
    assert "INDEX/SUBINDEX (0x6064, 0x1018/4)" in err


def test_read_help_lists_every_json_key(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["read", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    for key in ("node", "index", "subindex", "name", "type", "value", "meaning", "raw", "data"):
        assert f'"{key}"' in text, key


def test_read_decimal_index_and_json(dev: SocketResponder, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = cli(capsys, "read", dev.url, "1", "24676", "0x0", "--json")
    assert code == 0
    # Indexes as hex strings, as the text output and decode/monitor show them.
    assert json.loads(out) == {"node": 1, "index": "0x6064", "subindex": "0x00", "name": "Position actual value",
                               "type": "i32", "value": 1000, "raw": "e8030000", "data": "e8030000"}


def test_read_statusword_shows_its_cia402_state(capsys: pytest.CaptureFixture[str]) -> None:
    # 0x0040: bit 6 alone = "switch on disabled" (CiA 402-2 6.4.1.4, state coding);
    # 0x0637: operation enabled with voltage enabled, remote and target reached.
    script = dict([read_pair(2, 0x6041, 0, b"\x40\x00"), read_pair(3, 0x6041, 0, b"\x37\x06")])
    with SocketResponder(script) as dev:
        code, out, _ = cli(capsys, "read", dev.url, "2", "Statusword")
        assert (code, out) == (0, "40 00 -> u16 64 (0x0040) [switch on disabled]  Statusword\n")
        code, out, _ = cli(capsys, "read", dev.url, "3", "0x6041", "--json")
    assert json.loads(out)["meaning"] == "operation enabled, voltage enabled, remote, target reached"


def test_read_signed(dev: SocketResponder, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = cli(capsys, "read", dev.url, "1", "0x6077", "0", "--type", "i16")
    assert (code, out) == (0, "FB FF -> i16 -5 (0xFFFB)\n")


def test_read_str_by_segmented_read(dev: SocketResponder, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = cli(capsys, "read", dev.url, "1", "0x1008", "0", "--type", "str")
    assert code == 0 and out.endswith('-> str "EPOS4 Compact 50/8 CAN"  Manufacturer device name\n')
    code, out_eds, _ = cli(capsys, "read", dev.url, "1", "Manufacturer device name")  # VISIBLE_STRING
    assert (code, out_eds) == (0, out)
    code, out, _ = cli(capsys, "read", dev.url, "1", "0x1008", "0", "--type", "bytes", "--json")
    assert json.loads(out)["data"] == NAME.hex()


def test_write_int_types(dev: SocketResponder, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = cli(capsys, "write", dev.url, "1", "0x6040", "0", "0xF", "--type", "u16")
    assert (code, out) == (0, "wrote u16 15 (0x000F) [0F 00] to node 1 0x6040/0x00 Controlword\n")
    code, out, _ = cli(capsys, "write", dev.url, "1", "0x607A", "0", "-100", "--type", "i32")
    assert code == 0
    # By name, the type from the EDS (Controlword is UNSIGNED16, Target position INTEGER32).
    code, out, _ = cli(capsys, "write", dev.url, "1", "Controlword", "0xF")
    assert (code, out) == (0, "wrote u16 15 (0x000F) [0F 00] to node 1 0x6040/0x00 Controlword\n")
    code, out, _ = cli(capsys, "write", dev.url, "1", "target_position", "-100")
    assert code == 0 and out.startswith("wrote i32 -100 (0xFFFFFF9C) [9C FF FF FF]")


def test_write_str_by_segmented_write(dev: SocketResponder, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = cli(capsys, "write", dev.url, "0", "0x2100", "1", "123456789", "--type", "str")
    assert (code, err) == (0, "")


def test_segmented_write_to_a_remote_node_is_refused(dev: SocketResponder,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    before = dev.requests
    code, _, err = cli(capsys, "write", dev.url, "2", "0x2100", "1", "123456789", "--type", "str")
    assert code == 2 and "does not forward" in err and "Traceback" not in err
    assert dev.requests == before


def test_device_error_exits_1(dev: SocketResponder, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = cli(capsys, "read", dev.url, "2", "0x1234", "0")
    assert code == 1 and out == ""
    assert "0x06020000 Object does not exist error" in err and "Traceback" not in err


def test_timeout_exits_2(dev: SocketResponder, capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = cli(capsys, "read", dev.url, "3", "0x6064", "0", "--timeout", "0.05")
    assert code == 2 and "timeout" in err and "no answer within 0.05 s" in err
    assert "does not answer" not in err  # the EPOS4 itself answered: the node is to blame


def test_a_silent_epos4_is_named_not_the_node(capsys: pytest.CaptureFixture[str]) -> None:
    """Nothing answers at all, not even the EPOS4 asked as node 0 (guide chapter 5): one
    line naming the link and what to check, for a node behind it and for node 0."""
    with SocketResponder({}) as silent:
        for node in ("3", "0"):
            code, _, err = cli(capsys, "read", silent.url, node, "0x6064", "0", "--timeout", "0.05")
            assert code == 2 and len(err.splitlines()) == 1, err
            assert f"the EPOS4 at {silent.url} does not answer" in err
            assert "baud rate" in err and "power" in err and "node id" not in err


def test_unreachable_port_exits_2(capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = cli(capsys, "read", "/dev/does-not-exist", "1", "0x6064", "0")
    assert code == 2 and "cannot open /dev/does-not-exist" in err and "Traceback" not in err


def test_value_out_of_range_exits_2(dev: SocketResponder, capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = cli(capsys, "write", dev.url, "1", "0x6040", "0", "70000", "--type", "u16")
    assert code == 2 and "out of range for u16" in err


def test_bad_number_is_a_usage_error(dev: SocketResponder, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main(["read", dev.url, "1", "0x6064", "zz"])
    assert info.value.code == 2
    assert "not a decimal or 0x-hex number" in capsys.readouterr().err
    code, _, err = cli(capsys, "write", dev.url, "1", "0x6040", "0", "zz", "--type", "u16")
    assert code == 2 and "not a decimal or 0x-hex number" in err


def test_nmt(dev: SocketResponder, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = cli(capsys, "nmt", dev.url, "2", "start")
    assert (code, out) == (0, "sent NMT start to node 2\n")


def test_scan(capsys: pytest.CaptureFixture[str]) -> None:
    script = dict([read_pair(0, 0x1000, 0, struct.pack("<I", 0x00020192)),  # the link check
                   read_pair(1, 0x1000, 0, struct.pack("<I", 0x00020192)),
                   *segmented_read_pairs(1, 0x1008, 0, b"EPOS4"),
                   *[read_pair(1, 0x1018, s, struct.pack("<I", v)) for s, v in ((1, 0xFB), (2, 2), (3, 3), (4, 4))],
                   read_pair(1, 0x1018, 4, b"", code=0x06090011)][:-1])
    with SocketResponder(script) as dev:
        code, out, _ = cli(capsys, "scan", dev.url, "--nodes", "1-3", "--node-timeout", "0.05")
        assert code == 0
        assert out == ('node   1  type=0x00020192  name="EPOS4"  vendor=0x000000FB product=0x00000002 '
                       'revision=0x00000003 serial=0x00000004\n')
        code, out, _ = cli(capsys, "scan", dev.url, "--nodes", "1", "--json")
        assert json.loads(out)["name"] == "EPOS4"
        code, _, err = cli(capsys, "scan", dev.url, "--nodes", "2,3", "--node-timeout", "0.02")
        assert code == 2 and "no node answered" in err


def test_trace_then_replay(dev: SocketResponder, capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    trace = tmp_path / "session.txt"
    code, out, _ = cli(capsys, "read", dev.url, "1", "0x1008", "0", "--type", "str", "--trace", str(trace))
    assert code == 0
    text = trace.read_text()
    assert text.startswith("# epos-link capture v1\n# source: epos-link trace of socket://")
    assert text.count(" TX ") == 2 and text.count(" RX ") >= 2
    code, again, _ = cli(capsys, "read", f"replay://{trace}", "1", "0x1008", "0", "--type", "str")
    assert (code, again) == (0, out)
    # The recording fails loudly when asked something else.
    code, _, err = cli(capsys, "read", f"replay://{trace}", "1", "0x6064", "0")
    assert code == 2 and "ReplayMismatchError" in err and "expects the host to send" in err


@pytest.mark.skipif(os.name != "posix", reason="pseudo-terminals are POSIX")
def test_read_and_write_over_a_pty(capsys: pytest.CaptureFixture[str]) -> None:
    with PtyResponder(SCRIPT) as dev:
        assert dev.path.startswith("/dev/")
        code, out, _ = cli(capsys, "read", dev.path, "1", "0x6064", "0", "--baud", "115200")
        assert (code, out) == (0, "E8 03 00 00 -> i32 1000 (0x000003E8)  Position actual value\n")
        code, out, _ = cli(capsys, "write", dev.path, "1", "0x6040", "0", "15", "--type", "u16")
        assert (code, out) == (0, "wrote u16 15 (0x000F) [0F 00] to node 1 0x6040/0x00 Controlword\n")
        code, _, err = cli(capsys, "read", dev.path, "2", "0x1234", "0")
        assert code == 1 and "0x06020000" in err


def test_console_script_exit_codes_without_traceback(dev: SocketResponder) -> None:
    run = lambda *a: subprocess.run([sys.executable, "-m", "epos_link.cli", *a],  # noqa: E731
                                    capture_output=True, text=True, timeout=60)
    ok = run("read", dev.url, "1", "0x6064", "0")
    assert (ok.returncode, ok.stdout) == (0, "E8 03 00 00 -> i32 1000 (0x000003E8)  Position actual value\n")
    err = run("read", dev.url, "2", "0x1234", "0")
    assert err.returncode == 1 and "Traceback" not in err.stderr
    gone = run("read", "socket://127.0.0.1:1", "1", "0x6064", "0")
    assert gone.returncode == 2 and "Traceback" not in gone.stderr


def test_ports_lists_without_failing(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = cli(capsys, "ports", "--json")
    assert code == 0
    for line in out.splitlines():
        assert {"url", "kind", "id", "epos4"} <= set(json.loads(line))
    with pytest.raises(SystemExit):
        main(["ports", "--help"])
    assert "70-epos4.rules" in capsys.readouterr().out
