"""The README quick start, run as written against ``tcp-bridge serve --simulate``:
every ``$ tcp-bridge send`` line prints what the README shows, and exits as the
README says (0 all ACK, 1 any NAK or CAN). ``sleep N`` lines wait for the move
instead of sleeping: up to ten times N, polling 2R82, so a loaded machine does
not fail the test while the docs stay true on an idle one."""
from __future__ import annotations

import re
import select
import subprocess
import sys
import time
from pathlib import Path
from typing import Iterator

import pytest

ROOT = Path(__file__).resolve().parent.parent
PROMPT = "$ .venv/bin/tcp-bridge "


def quick_start() -> list[tuple[str, list[str]]]:
    """(command, expected output lines) of the README's first console block."""
    text = (ROOT / "README.md").read_text()
    block = re.search(r"In a second terminal:\n\n```console\n(.*?)```", text, re.S)
    assert block is not None, "the README's quick start block moved"
    steps: list[tuple[str, list[str]]] = []
    for line in block.group(1).splitlines():
        if line.startswith("$ "):
            steps.append((line[2:].split("#", 1)[0].strip(), []))
        else:
            steps[-1][1].append(line)
    return steps


def send(port: int, command: str) -> subprocess.CompletedProcess[str]:
    args = command[len(PROMPT) - 2:].split()[1:]  # after "send"
    args[0] = f"127.0.0.1:{port}"
    return subprocess.run([sys.executable, "-m", "tcp_bridge.cli", "send", *args], cwd=ROOT,
                          capture_output=True, text=True, timeout=60)


@pytest.fixture()
def bridge(tmp_path: Path) -> Iterator[int]:
    proc = subprocess.Popen([sys.executable, "-m", "tcp_bridge.cli", "serve", "--simulate",
                             "--port", "0", "--maintenance-port", "-1",
                             "--state-file", str(tmp_path / "state.json")],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        assert proc.stdout is not None
        ready, _, _ = select.select([proc.stdout], [], [], 60)
        assert ready, "the bridge did not start"
        line = proc.stdout.readline()
        found = re.search(r"listening on 127\.0\.0\.1:(\d+)", line)
        assert found, line
        yield int(found.group(1))
    finally:
        proc.terminate()
        proc.communicate(timeout=60)


def test_the_quick_start_prints_what_the_readme_shows(bridge: int) -> None:
    steps = quick_start()
    assert any(cmd.startswith("sleep ") for cmd, _ in steps), "the README must say to wait"
    for command, expected in steps:
        if command.startswith("sleep "):
            deadline = time.monotonic() + 10 * float(command.split()[1])
            while "2 R 82=1" not in send(bridge, PROMPT[2:] + "send x 2R82").stdout:
                assert time.monotonic() < deadline, "the quick start move did not finish"
                time.sleep(0.1)
            continue
        assert command.startswith(PROMPT[2:] + "send "), command
        p = send(bridge, command)
        assert p.stdout.splitlines() == expected, p.stderr
        # The README: exit 0 when every reply is ACK, 1 when any is NAK or CAN.
        assert p.returncode == (0 if all(line.endswith(" ACK") for line in expected) else 1)
