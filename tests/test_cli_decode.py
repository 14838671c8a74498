"""`epos-link decode` as a user runs it: a real subprocess."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

FIXTURE = Path(__file__).resolve().parent.parent / "fixtures" / "guide_read_home_position.txt"


def decode(*args: str, stdin: str = "") -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "epos_link", "decode", *args], input=stdin,
                          capture_output=True, text=True, timeout=30)


def test_request_hex_in_one_argument() -> None:
    out = decode("9002600201B030002E62", "--json")
    assert out.returncode == 0, out.stderr
    (obj,) = [json.loads(line) for line in out.stdout.splitlines()]
    assert obj["opcode"] == 0x60 and obj["name"] == "ReadObject"
    assert (obj["node"], obj["index"], obj["subindex"]) == (1, "0x30B0", "0x00")
    assert obj["data"] == "" and obj["error_code"] is None and obj["crc_ok"] is True


def test_answer_hex_in_many_arguments() -> None:
    args = "90 02 00 04 00 00 00 00 01 90 90 00 00 9A 5C".split()
    out = decode(*args, "--responses", "--json")
    assert out.returncode == 0, out.stderr
    (obj,) = [json.loads(line) for line in out.stdout.splitlines()]
    assert obj["opcode"] == 0 and obj["error_code"] == 0 and obj["crc_ok"] is True
    assert bytes.fromhex(obj["data"]) == bytes.fromhex("01 90 00 00")
    assert obj["node"] is None and obj["index"] is None and obj["subindex"] is None


def test_text_output() -> None:
    out = decode("90 02 00 04 00 00 00 00 01 90 90 00 00 9A 5C", "--responses")
    # monitor's line format; bare hex has no times, so no timestamp column.
    assert out.stdout == "RX Answer                         data [01 90 00 00] ok crc ok\n"


def test_stdin_hex() -> None:
    out = decode(stdin="90 02 60 02 01 B0 30 00 2E 62\n")
    assert out.stdout == "-- ReadObject                     node 1 0x30B0/0x00 Home position crc ok\n"


def test_a_capture_decodes_to_monitors_lines_with_its_timestamps() -> None:
    # The capture's times (guide Table 2-5/2-6 exchange, answer at 0.000868 s) and the
    # line format of epos-link monitor (epos_link/tools/view.py), -x as in monitor.
    out = decode(str(FIXTURE), "-x")
    assert out.returncode == 0, out.stderr
    assert out.stdout.splitlines() == [
        "(000.000000) TX ReadObject                     node 1 0x30B0/0x00 Home position crc ok"
        "  [90 02 60 02 01 B0 30 00 2E 62]",
        "(000.000868) RX Answer(ReadObject)             node 1 0x30B0/0x00 Home position"
        " = 36865 (0x00009001) ok crc ok 0.868 ms  [90 02 00 04 00 00 00 00 01 90 90 00 00 9A 5C]",
    ]


@pytest.mark.parametrize("how", ["--file", "positional"])
def test_fixture_file(how: str) -> None:
    args = ["--file", str(FIXTURE)] if how == "--file" else [str(FIXTURE)]
    out = decode(*args, "--json")
    assert out.returncode == 0, out.stderr
    tx, rx = [json.loads(line) for line in out.stdout.splitlines()]
    assert tx["direction"] == "TX" and tx["index"] == "0x30B0"
    assert rx["direction"] == "RX" and rx["name"] == "ReadObjectAnswer"
    assert rx["data"] == "01900000"


def test_bad_crc_and_junk_are_reported() -> None:
    out = decode("ff 90 02 60 02 01 B0 30 00 2E 63 aa", "--json")
    assert out.returncode == 1
    objs = [json.loads(line) for line in out.stdout.splitlines()]
    assert [o["name"] for o in objs] == ["not a frame", "ReadObject", "not a frame"]
    assert objs[1]["crc_ok"] is False
    assert objs[0]["raw"] == "ff" and objs[2]["raw"] == "aa"


@pytest.mark.parametrize("args,stdin", [(["zz"], ""), ([], ""), (["--file", "/nonexistent"], "")])
def test_bad_input_is_a_message_not_a_traceback(args: list[str], stdin: str) -> None:
    out = decode(*args, stdin=stdin)
    assert out.returncode == 2
    assert "Traceback" not in out.stderr and "epos-link decode:" in out.stderr


@pytest.mark.parametrize("name", ["/nonexistent.txt", "cap.txt", "captures/today"])
def test_a_missing_file_is_named_as_such(name: str) -> None:
    # Hex never holds "/" or ".": such an argument names a file, and a missing one is
    # "no such file", not "not hex bytes".
    out = decode(name)
    assert out.returncode == 2
    assert out.stderr == f"epos-link decode: {name}: no such file\n"


# Issue 24: a 6 MB line gave a 1 MiB error line. Cut at 1 MiB to bound memory
# (epos_link/tools/follow.py), its error quotes 40 characters and says the length.
SIX_MB = 3_000_000


@pytest.mark.parametrize("text,message", [
    ("ZZ" * SIX_MB, "not hex bytes: 'ZZZZ"),  # not hex
    ("0.0 TX " + "ZZ" * SIX_MB, "line 1: longer than 1048576 characters, which no capture "
                                "record is"),
    ("0.0 TX " + "AB" * SIX_MB, "line 1: longer than 1048576 characters"),  # hex, but too long
    ("0.0 TX 90 02\n1.0 RX " + "A" * SIX_MB, "line 2: longer than 1048576 characters"),
], ids=["not-hex", "record-not-hex", "record-hex", "second-line"])  # a 6 MB id in
# PYTEST_CURRENT_TEST, which every child inherits, makes exec fail (E2BIG) on pytest < 9.2
@pytest.mark.parametrize("how", ["stdin", "file"])
def test_a_6_mb_line_gives_a_short_error_line(tmp_path: Path, text: str, message: str,
                                              how: str) -> None:
    path = tmp_path / "big.txt"
    path.write_text(text + "\n")
    p = decode("-f", str(path)) if how == "file" else decode(stdin=text + "\n")
    assert p.returncode == 2 and "Traceback" not in p.stderr
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and len(lines[0]) < 200 and message in lines[0], lines[0][:300]


def test_a_hex_line_of_6_mb_is_decoded_across_the_cut() -> None:
    p = decode(stdin="90 02 " + "AB" * SIX_MB + "\n")
    assert p.returncode == 1 and "Traceback" not in p.stderr  # junk, reported, bounded
    assert max(len(line) for line in p.stdout.splitlines()) < 4000


def test_a_frame_cut_before_a_lone_dle_does_not_hide_the_next_one() -> None:
    """Issue 35: the guide's ReadObject request (2.2.9, Table 2-5) after `90 02 00 90`
    (a frame cut after its opcode and a lone DLE) decodes as it does alone."""
    alone = decode("90 02 60 02 01 B0 30 00 2E 62")
    out = decode("90 02 00 90 90 02 60 02 01 B0 30 00 2E 62")
    assert out.stdout.splitlines() == [
        "-- not a frame: Len 144 words exceeds 143 [90 02 00 90]",
        *alone.stdout.splitlines()]
