"""``epos-link backup`` and ``restore`` against the simulator over TCP (issue 11, Must show 3)."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Iterator

import canopen
import pytest

from epos_link.client import EposClient
from epos_link.simulator.core import Epos4Simulator
from epos_link.simulator.link import TcpLink

# Three parameters (CiA 402): Profile velocity 6081h (u32), Home offset 607Ch (i32),
# Max position limit 607Dh/02 (i32).
CHANGES = [((0x6081, 0), 777), ((0x607C, 0), -3), ((0x607D, 2), 5555)]


@pytest.fixture()
def drive() -> Iterator[str]:
    sim = Epos4Simulator(1, [2])
    link = TcpLink(sim).start()
    try:
        yield link.url
    finally:
        link.close()
        sim.close()


def cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "epos_link.cli", *args], capture_output=True, text=True, timeout=120)


def values(url: str) -> dict[tuple[int, int], int]:
    with EposClient.open(url) as c:
        return {key: int.from_bytes(c.read_object(2, *key), "little", signed=True) for key, _ in CHANGES}


def change(url: str) -> None:
    with EposClient.open(url) as c:
        for (index, sub), value in CHANGES:
            c.write_object(2, index, sub, value.to_bytes(4, "little", signed=True))


def test_backup_change_restore(drive: str, tmp_path: Path) -> None:
    dcf = tmp_path / "node2.dcf"
    original = values(drive)
    p = cli("backup", drive, "2", "-o", str(dcf))
    assert p.returncode == 0, p.stderr
    assert "wrote" in p.stderr and "read" in p.stderr
    # canopen loads it, values included (CiA 306 ParameterValue).
    od = canopen.import_od(str(dcf), 2)
    assert od[0x6081].value == original[(0x6081, 0)]
    assert od[0x1008].value == "EPOS4"
    assert od.node_id == 2

    change(drive)
    changed = values(drive)
    assert changed == {key: value for key, value in CHANGES}

    dry = cli("restore", drive, "2", str(dcf), "--dry-run")
    assert dry.returncode == 0, dry.stderr
    assert values(drive) == changed  # a dry run writes nothing
    differs = [line for line in dry.stdout.splitlines() if line.startswith("differs")]
    assert len(differs) == 3
    assert "differs   0x6081/0x00 Profile velocity: 777 (0x00000309) -> 1000 (0x000003E8) (dry run: not written)" in dry.stdout
    assert not any(line.startswith("written") for line in dry.stdout.splitlines())
    assert "(dry run)" in dry.stderr

    p = cli("restore", drive, "2", str(dcf))
    assert p.returncode == 0, p.stderr
    assert values(drive) == original
    written = [line.split()[1] for line in p.stdout.splitlines() if line.startswith("written")]
    assert written == ["0x607C/0x00", "0x607D/0x02", "0x6081/0x00"]
    assert "skipped   0x6064/0x00 Position actual value: ro (read-only)" in p.stdout
    assert "skipped   0x6040/0x00 Controlword: controlword" in p.stdout  # a command, never restored
    assert "3 written" in p.stderr

    again = cli("restore", drive, "2", str(dcf))
    assert again.returncode == 0 and not any(line.startswith("written") for line in again.stdout.splitlines())


def test_refused_objects_do_not_stop_the_rest(drive: str, tmp_path: Path) -> None:
    dcf = tmp_path / "node2.dcf"
    assert cli("backup", drive, "2", "-o", str(dcf)).returncode == 0
    # An object the drive does not have: it answers 0x06020000 (guide Table 6-21).
    text = dcf.read_text() + ("\n[5000]\nParameterName=Not on this drive\nObjectType=0x7\nDataType=0x0007\n"
             "AccessType=rw\nPDOMapping=0\nParameterValue=0x1\n")
    dcf.write_text(text)
    od = canopen.import_od(str(dcf), 2)
    assert 0x5000 in od
    change(drive)
    p = cli("restore", drive, "2", str(dcf))
    assert p.returncode == 1, p.stderr
    assert "refused   0x5000/0x00 Not on this drive: 0x06020000 Object does not exist error" in p.stdout
    assert sum(line.startswith("written") for line in p.stdout.splitlines()) == 3  # the rest still restored
    assert "1 refused" in p.stderr


def test_restore_refuses_an_enabled_drive(drive: str, tmp_path: Path) -> None:
    dcf = tmp_path / "node2.dcf"
    assert cli("backup", drive, "2", "-o", str(dcf)).returncode == 0
    with EposClient.open(drive) as c:  # CiA 402: shutdown, switch on, enable operation
        for cw in (0x06, 0x07, 0x0F):
            c.write_object(2, 0x6040, 0, cw.to_bytes(2, "little"))
        sw = int.from_bytes(c.read_object(2, 0x6041, 0)[:2], "little")
    assert sw & 0x6F == 0x27
    p = cli("restore", drive, "2", str(dcf))
    assert p.returncode == 2 and "operation enabled" in p.stderr and "--force" in p.stderr
    assert p.stdout == ""


def test_usage_errors_are_one_line(tmp_path: Path) -> None:
    p = cli("restore", "sim://", "2", str(tmp_path / "missing.dcf"))
    assert p.returncode == 2 and "no such file" in p.stderr and "Traceback" not in p.stderr
    p = cli("backup", "sim://", "2", "--eds", str(tmp_path / "missing.eds"), "-o", str(tmp_path / "x.dcf"))
    assert p.returncode == 2 and "no such file" in p.stderr and "Traceback" not in p.stderr


@pytest.mark.skipif(not hasattr(__import__("os"), "openpty"), reason="needs a pseudo-terminal")
def test_progress_bar_on_a_terminal(drive: str, tmp_path: Path) -> None:
    import os
    import select

    master, slave = os.openpty()
    try:
        p = subprocess.run([sys.executable, "-m", "epos_link.cli", "backup", drive, "2", "-o", str(tmp_path / "x.dcf")],
                           stdout=subprocess.PIPE, stderr=slave, text=True, timeout=120)
        os.close(slave)
        slave = -1
        seen = b""
        while select.select([master], [], [], 0.5)[0]:
            try:
                chunk = os.read(master, 65536)
            except OSError:
                break
            if not chunk:
                break
            seen += chunk
    finally:
        os.close(master)
        if slave >= 0:
            os.close(slave)
    assert p.returncode == 0
    text = seen.decode(errors="replace")
    assert "\r[" in text and "] 1/" in text and "Device type" in text
    assert "read" in text and "wrote" in text  # the summary


def test_backup_to_standard_output(drive: str, tmp_path: Path) -> None:
    # "-o -" is standard output, as everywhere else in epos-link: no file named "-".
    import os

    # Run in tmp_path (a file named "-" would appear there), this checkout first on the path.
    root = str(Path(__file__).resolve().parent.parent)
    env = {**os.environ, "PYTHONPATH": root + os.pathsep + os.environ.get("PYTHONPATH", "")}
    p = subprocess.run([sys.executable, "-m", "epos_link.cli", "backup", drive, "2", "-o", "-"],
                       capture_output=True, text=True, timeout=120, cwd=tmp_path, env=env)
    assert p.returncode == 0, p.stderr
    assert not (tmp_path / "-").exists()
    assert "[1008]" in p.stdout and "ParameterValue=EPOS4" in p.stdout
    assert "wrote standard output" in p.stderr
    dcf = tmp_path / "out.dcf"
    dcf.write_text(p.stdout)
    assert canopen.import_od(str(dcf), 2)[0x1008].value == "EPOS4"  # the whole DCF, loadable


def test_restore_changes_only(drive: str, tmp_path: Path) -> None:
    dcf = tmp_path / "node2.dcf"
    assert cli("backup", drive, "2", "-o", str(dcf)).returncode == 0
    change(drive)
    p = cli("restore", drive, "2", str(dcf), "--changes-only")
    assert p.returncode == 0, p.stderr
    # Only the three objects it wrote, not the ~100 unchanged or skipped around them.
    assert [line.split()[:2] for line in p.stdout.splitlines()] == [
        ["written", "0x607C/0x00"], ["written", "0x607D/0x02"], ["written", "0x6081/0x00"]]
    assert "3 written" in p.stderr and "unchanged" in p.stderr  # the summary counts all


def test_interrupted_restore_prints_its_summary(drive: str, tmp_path: Path,
                                                monkeypatch: pytest.MonkeyPatch,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    """Ctrl-C during the writes: the summary of what was done, exit 130. The Ctrl-C
    arrives (as KeyboardInterrupt, what Python makes of SIGINT) in the second write."""
    from epos_link.cli import main
    from epos_link.tools import backup as backup_tool

    dcf = tmp_path / "node2.dcf"
    assert cli("backup", drive, "2", "-o", str(dcf)).returncode == 0
    change(drive)
    real_open = backup_tool.open_client

    def open_client(args):  # type: ignore[no-untyped-def]
        client = real_open(args)
        real_download = client.download
        writes = []

        def download(*a, **k):  # type: ignore[no-untyped-def]
            writes.append(a)
            if len(writes) == 2:
                raise KeyboardInterrupt
            return real_download(*a, **k)

        client.download = download  # type: ignore[method-assign]
        return client

    monkeypatch.setattr(backup_tool, "open_client", open_client)
    code = main(["restore", drive, "2", str(dcf), "--no-progress"])
    out, err = capsys.readouterr()
    assert code == 130
    assert [line.split()[0] for line in out.splitlines() if line.startswith("written")] == ["written"]
    assert "epos-link restore: interrupted: " in err and "1 written" in err
