"""``decode --follow``, standard input decoded as it arrives, and ``--trace -``."""
from __future__ import annotations

import os
import select
import subprocess
import sys
from pathlib import Path

from epos_link.cli import main

WAIT = 30.0
TX = "0.000000 TX 90 02 60 02 01 B0 30 00 2E 62\n"                 # guide Table 2-5
RX = "0.000868 RX 90 02 00 04 00 00 00 00 01 90 90 00 00 9A 5C\n"  # guide Table 2-6


def readline(proc: subprocess.Popen) -> str:  # type: ignore[type-arg]
    ready, _, _ = select.select([proc.stdout], [], [], WAIT)
    assert ready, "no decoded line arrived"
    return proc.stdout.readline()  # type: ignore[no-any-return, union-attr]


def test_follow_a_growing_capture(tmp_path: Path) -> None:
    cap = tmp_path / "cap.txt"
    cap.write_text("# epos-link capture v1\n" + TX)
    proc = subprocess.Popen([sys.executable, "-m", "epos_link.cli", "decode", "--follow", str(cap),
                             "--idle-exit", "5"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert readline(proc).startswith("(000.000000) TX ReadObject                     node 1 0x30B0/0x00")
        with cap.open("a") as fh:  # the capture grows while decode runs
            fh.write(RX)
        line = readline(proc)
        assert line.startswith("(000.000868) RX Answer(ReadObject)") and "Home position = 36865 (0x00009001)" in line
        assert proc.poll() is None
    finally:
        out, err = proc.communicate(timeout=WAIT)
    assert proc.returncode == 0, err


def test_standard_input_is_decoded_as_it_arrives() -> None:
    proc = subprocess.Popen([sys.executable, "-m", "epos_link.cli", "decode", "--json"], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert proc.stdin is not None
    try:
        proc.stdin.write(TX)
        proc.stdin.flush()
        first = readline(proc)  # standard input is still open
        assert '"name": "ReadObject"' in first and '"object": "Home position"' in first
        out, err = proc.communicate(input=RX, timeout=WAIT)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    assert '"value": 36865' in out


def test_hex_on_standard_input_still_works() -> None:
    p = subprocess.run([sys.executable, "-m", "epos_link.cli", "decode"], input="90 02 60 02 01 B0 30 00 2E 62\n",
                       capture_output=True, text=True, timeout=WAIT)
    assert p.returncode == 0 and p.stdout.startswith("-- ReadObject                     node 1 0x30B0/0x00")


def test_trace_dash_writes_to_standard_output(capsys) -> None:  # type: ignore[no-untyped-def]
    code = main(["read", "sim://", "0", "0x1000", "--trace", "-"])
    out = capsys.readouterr().out
    assert code == 0 and not os.path.exists("-")
    lines = out.splitlines()
    assert lines[0] == "# epos-link capture v1"
    assert any(" TX 90 02 60 02 00 00 10 00 " in line for line in lines)  # ReadObject node 0 0x1000/0
    assert any(" RX 90 02 00 04 00 00 00 00 " in line for line in lines)
    assert lines[-1].endswith("Device type")
