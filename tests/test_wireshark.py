"""The Lua dissector under Debian's tshark (Wireshark 4.0 baseline), ``epos-link export``,
``wireshark path | install`` and the extcap entry (issue 11, Must show 2)."""
from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from epos_link.codes import CIA301_EXTRA, ERROR_TABLE
from epos_link.tools.pcapng import FLAG_INBOUND, FLAG_OUTBOUND, read_pcapng
from epos_link.tools.wireshark import dissector_path

FIXTURES = Path(__file__).resolve().parent.parent / "fixtures"
TSHARK = shutil.which("tshark")
needs_tshark = pytest.mark.skipif(TSHARK is None, reason="tshark is not installed "
                                  "(Debian: apt-get install tshark); the dissector is not exercised")


def cli(*args: str, env: "dict[str, str] | None" = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "epos_link.cli", *args], capture_output=True, text=True,
                          timeout=60, env={**os.environ, **(env or {})})


def tshark(*args: str, env: "dict[str, str] | None" = None) -> list[str]:
    assert TSHARK is not None
    p = subprocess.run([TSHARK, *args], capture_output=True, text=True, timeout=120,
                       env={**os.environ, **(env or {})})
    assert p.returncode == 0, p.stderr
    assert "Lua: Error" not in p.stderr and "Lua: Error" not in p.stdout, p.stderr
    return p.stdout.splitlines()


def export(tmp_path: Path, capture: str, name: str = "out.pcapng") -> Path:
    out = tmp_path / name
    p = cli("export", str(FIXTURES / capture), "-o", str(out))
    assert p.returncode == 0, p.stderr
    return out


def test_export_writes_one_packet_per_frame_with_its_direction(tmp_path: Path) -> None:
    out = export(tmp_path, "guide_read_home_position.txt")
    interfaces, packets = read_pcapng(out.read_bytes())
    assert interfaces[0].linktype == 147
    # Guide 2.2.9 Tables 2-5 and 2-6, as on the wire (the answer's 0x90 stuffed).
    assert [(p.flags, p.data.hex(" ").upper()) for p in packets] == [
        (FLAG_OUTBOUND, "90 02 60 02 01 B0 30 00 2E 62"),
        (FLAG_INBOUND, "90 02 00 04 00 00 00 00 01 90 90 00 00 9A 5C")]
    assert packets[1].time_ns - packets[0].time_ns == 868_000  # 0.000868 s in the capture


def test_export_usage_errors(tmp_path: Path) -> None:
    p = cli("export", str(tmp_path / "missing.txt"), "-o", str(tmp_path / "x.pcapng"))
    assert p.returncode == 2 and "No such file" in p.stderr and "Traceback" not in p.stderr
    binary = tmp_path / "bin.txt"
    binary.write_bytes(b"\xff\xfe\x00")
    p = cli("export", str(binary), "-o", str(tmp_path / "x.pcapng"))
    assert p.returncode == 2 and "not a capture file" in p.stderr


READ = "TX 90 02 60 02 01 B0 30 00 2E 62"  # guide 2.2.9 Table 2-5


@pytest.mark.parametrize("time,message", [
    ("nan", "line 1: bad time 'nan': not a finite number"),
    ("inf", "line 1: bad time 'inf': not a finite number"),
    ("-inf", "line 1: bad time '-inf': not a finite number"),
    ("1e300", "a record at 1e+300 s is farther from the capture's start than a pcapng "
              "timestamp reaches"),
    ("-1e300", "a record at -1e+300 s is farther"),
])
def test_export_of_a_time_pcapng_cannot_hold_is_one_line(tmp_path: Path, time: str,
                                                          message: str) -> None:
    capture = tmp_path / "c.txt"
    capture.write_text(f"{time} {READ}\n")
    p = cli("export", str(capture), "-o", str(tmp_path / "x.pcapng"))
    assert p.returncode == 2 and "Traceback" not in p.stderr, p.stderr
    assert len(p.stderr.strip().splitlines()) == 1 and message in p.stderr


@pytest.mark.parametrize("start", ["# start: nan", "# start: inf", "# start: x", ""])
def test_export_falls_back_to_the_files_time_for_a_start_that_is_no_time(
        tmp_path: Path, start: str) -> None:
    capture = tmp_path / "c.txt"
    capture.write_text(f"{start}\n0.5 {READ}\n")
    os.utime(capture, (1_700_000_000.5, 1_700_000_000.5))
    p = cli("export", str(capture), "-o", str(tmp_path / "x.pcapng"))
    assert p.returncode == 0, p.stderr
    _, packets = read_pcapng((tmp_path / "x.pcapng").read_bytes())
    assert [p.time_ns for p in packets] == [1_700_000_000_500_000_000]  # the file's mtime


def test_export_start_past_the_year_2554_is_one_line(tmp_path: Path) -> None:
    capture = tmp_path / "c.txt"
    capture.write_text(f"0.5 {READ}\n")
    for args in (["--start", "1e300"], ["--start", "18446744074"]):
        p = cli("export", str(capture), "-o", str(tmp_path / "x.pcapng"), *args)
        assert p.returncode == 2 and "Traceback" not in p.stderr, p.stderr
        assert "past what a pcapng timestamp holds (2**64 ns, the year 2554)" in p.stderr


def test_lua_error_names_match_the_guide_table() -> None:
    lua = dissector_path().read_text()
    names = {int(code, 16): name for code, name in re.findall(r'\[0x([0-9A-F]{8})\] = "([^"]+)"', lua)}
    expected = {code: info.name for code, info in {**ERROR_TABLE, **CIA301_EXTRA}.items()}
    assert names == expected
    assert 'DissectorTable.get("wtap_encap"):add(wtap.USER0, maxon)' in lua


def test_wireshark_path() -> None:
    p = cli("wireshark", "path")
    assert p.returncode == 0 and Path(p.stdout.strip()) == dissector_path() and dissector_path().is_file()


@needs_tshark
def test_tshark_reads_an_exported_capture(tmp_path: Path) -> None:
    """The command of docs/epos-link.md (Wireshark), exactly."""
    out = export(tmp_path, "guide_read_home_position.txt")
    lua = cli("wireshark", "path").stdout.strip()
    lines = tshark("-X", f"lua_script:{lua}", "-r", str(out), "-T", "fields",
                   "-e", "maxon.opcode", "-e", "maxon.index", "-e", "frame.p2p_dir")
    assert lines == ["0x60\t0x30b0\t0", "0x00\t0x30b0\t1"]


@needs_tshark
def test_tshark_fields_of_a_segmented_read(tmp_path: Path) -> None:
    out = export(tmp_path, "client_segmented_read_inline.txt")
    lines = tshark("-X", f"lua_script:{dissector_path()}", "-r", str(out), "-T", "fields", "-E", "separator=|",
                   "-e", "maxon.opcode", "-e", "maxon.node", "-e", "maxon.subindex", "-e", "maxon.error_code",
                   "-e", "maxon.crc", "-e", "maxon.crc_ok", "-e", "maxon.request_in", "-e", "_ws.col.Info")
    assert lines[0] == "0x81|1|0x00||0xa303|1||InitiateSegmentedRead node 1 0x1008/0x00"
    assert lines[1] == ("0x00|1|0x00|0x00000000|0x4fd4|1|1|"
                        "Answer to InitiateSegmentedRead node 1 0x1008/0x00: ok object length 22")
    assert lines[5].startswith("0x00|1|0x00|0x00000000|0xdc7a|1|5|Answer to SegmentRead node 1 0x1008/0x00")


@needs_tshark
def test_tshark_flags_a_bad_crc_junk_and_names_error_codes(tmp_path: Path) -> None:
    capture = tmp_path / "bad.txt"
    capture.write_text(
        "# epos-link capture v1\n"
        "0.0 TX 90 02 60 02 01 B0 30 00 2E 62\n"                           # guide Table 2-5
        "0.1 RX AA BB 90 02 00 04 00 00 00 00 01 90 90 00 00 9A 00\n"     # junk, Table 2-6 with a bad CRC
        "0.2 TX 90 02 60 02 01 B0 30 00 2E 62\n"
        "0.3 RX 90 02 00 04 00 00 02 06 00 00 00 00 57 64\n")            # 0x06020000
    out = tmp_path / "bad.pcapng"
    assert cli("export", str(capture), "-o", str(out)).returncode == 0
    lines = tshark("-X", f"lua_script:{dissector_path()}", "-r", str(out), "-T", "fields", "-E", "separator=|",
                   "-e", "maxon.crc_ok", "-e", "maxon.error_code", "-e", "_ws.col.Info")
    assert lines[1] == "||Not a frame (2 bytes)"
    assert lines[2].startswith("0|0x00000000|Answer to ReadObject") and lines[2].endswith("[CRC BAD]")
    assert lines[4].startswith("1|0x06020000|Answer to ReadObject node 1 0x30B0/0x00: "
                               "0x06020000 Object does not exist error")


@needs_tshark
def test_install_puts_the_dissector_where_wireshark_finds_it(tmp_path: Path) -> None:
    env = {"HOME": str(tmp_path), "XDG_CONFIG_HOME": str(tmp_path / ".config")}
    p = cli("wireshark", "install", env=env)
    assert p.returncode == 0, p.stderr
    lua = tmp_path / ".local" / "lib" / "wireshark" / "plugins" / "maxon_serial_v2.lua"
    assert lua.read_text() == dissector_path().read_text()
    out = export(tmp_path, "guide_read_home_position.txt")
    # No -X: tshark loads the personal plugin by itself, and the dissector its objects.
    assert tshark("-r", str(out), "-T", "fields", "-e", "maxon.opcode", "-e", "maxon.object",
                  env=env) == ["0x60\tHome position", "0x00\tHome position"]
    assert "WIRESHARK_EXTCAP_DIR=" in p.stderr  # 4.0 has no personal extcap folder: install says so


@needs_tshark
@pytest.mark.skipif(hasattr(os, "geteuid") and os.geteuid() == 0,
                    reason="Wireshark ignores WIRESHARK_EXTCAP_DIR when run as root (wsutil "
                    "started_with_special_privs), so tshark -D cannot list the entry here")
def test_tshark_lists_the_extcap_interface(tmp_path: Path) -> None:
    p = cli("wireshark", "install", "--lua-dir", str(tmp_path / "lua"), "--extcap-dir", str(tmp_path / "extcap"))
    assert p.returncode == 0, p.stderr
    listed = tshark("-D", env={"HOME": str(tmp_path), "WIRESHARK_EXTCAP_DIR": str(tmp_path / "extcap")})
    assert any("maxon" in line and "epos-link monitor" in line for line in listed)


def test_extcap_entry_answers_wireshark(tmp_path: Path) -> None:
    p = cli("wireshark", "install", "--lua-dir", str(tmp_path / "lua"), "--extcap-dir", str(tmp_path / "extcap"))
    assert p.returncode == 0, p.stderr
    entry = tmp_path / "extcap" / "epos_link_extcap"
    if os.name == "nt":
        pytest.skip("the .bat entry is not run here")
    run = lambda *a: subprocess.run([str(entry), *a], capture_output=True, text=True, timeout=60)  # noqa: E731
    assert "interface {value=maxon}" in run("--extcap-interfaces").stdout
    assert run("--extcap-interface", "maxon", "--extcap-dlts").stdout.startswith("dlt {number=147}")
    assert "{call=--device}" in run("--extcap-interface", "maxon", "--extcap-config").stdout
    bad = run("--capture")
    assert bad.returncode == 2 and "Traceback" not in bad.stderr


def test_extcap_capture_writes_pcapng_through_the_monitor(tmp_path: Path) -> None:
    """What Wireshark does when capturing from the "maxon" interface: run the entry with
    --capture --fifo PATH, then stop it with SIGTERM (a plain file stands in for the fifo)."""
    import select
    import signal
    import socket
    import time

    from epos_link.client import EposClient

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    fifo = tmp_path / "fifo.pcapng"
    proc = subprocess.Popen([sys.executable, "-m", "epos_link.tools.extcap", "--capture", "--extcap-interface",
                             "maxon", "--fifo", str(fifo), "--device", "sim://?drives=2",
                             "--listen", f"127.0.0.1:{port}"], stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 30
        while True:  # the entry prints nothing: wait for its listener (bounded)
            try:
                client = EposClient.open(f"socket://127.0.0.1:{port}")
                break
            except Exception:
                assert time.monotonic() < deadline and proc.poll() is None, "the extcap capture did not start"
                select.select([], [], [], 0.1)
        with client:
            client.read_object(2, 0x6081, 0)
    finally:
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    interfaces, packets = read_pcapng(fifo.read_bytes())
    assert interfaces[0].linktype == 147
    assert [p.flags for p in packets] == [FLAG_OUTBOUND, FLAG_INBOUND]
    assert packets[0].data == bytes.fromhex("90 02 60 02 02 81 60 00 D6 3B")  # ReadObject node 2 0x6081/0


@needs_tshark
def test_installed_dissector_names_objects_and_types_values(tmp_path: Path) -> None:
    """install generates the objects table from the EDS; the dissector shows the name and
    the typed value (the statusword with its CiA 402 state), as monitor does."""
    from tests.reference import reference_frame

    p = cli("wireshark", "install", "--lua-dir", str(tmp_path / "lua"), "--no-extcap")
    assert p.returncode == 0, p.stderr
    assert (tmp_path / "lua" / "maxon_serial_v2.objects").is_file()

    def hexed(frame: bytes) -> str:
        return frame.hex(" ").upper()

    ok = (0).to_bytes(4, "little")
    capture = tmp_path / "sw.txt"
    capture.write_text("# epos-link capture v1\n" + "".join(f"{t} {d} {hexed(b)}\n" for t, d, b in [
        # ReadObject node 2 0x6041/0 (guide 2.1.1.1), answer 0x0240: switch on disabled, remote
        (0.0, "TX", reference_frame(0x60, bytes((2,)) + (0x6041).to_bytes(2, "little") + b"\x00")),
        (0.001, "RX", reference_frame(0x00, ok + b"\x40\x02\x00\x00")),
        # WriteObject node 2 0x607A/0 Target position = -100 (INTEGER32; guide 2.1.2.1)
        (0.002, "TX", reference_frame(0x68, bytes((2,)) + (0x607A).to_bytes(2, "little") + b"\x00"
                                      + (-100).to_bytes(4, "little", signed=True))),
        (0.003, "RX", reference_frame(0x00, ok)),
    ]))
    out = tmp_path / "sw.pcapng"
    assert cli("export", str(capture), "-o", str(out)).returncode == 0
    lines = tshark("-X", f"lua_script:{tmp_path / 'lua' / 'maxon_serial_v2.lua'}", "-r", str(out),
                   "-T", "fields", "-E", "separator=|", "-e", "maxon.object", "-e", "maxon.value",
                   "-e", "_ws.col.Info")
    assert lines[0] == "Statusword||ReadObject node 2 0x6041/0x00 Statusword"
    assert lines[1].startswith("Statusword|576 (0x0240) [switch on disabled, remote]|Answer to ReadObject "
                               "node 2 0x6041/0x00 Statusword = 576 (0x0240) [switch on disabled, remote]: ok")
    assert lines[2].startswith("Target position|-100 (0xFFFFFF9C)|WriteObject node 2 0x607A/0x00 "
                               "Target position = -100 (0xFFFFFF9C)")
    assert lines[3].startswith("Target position||Answer to WriteObject node 2 0x607A/0x00 Target position: ok")
