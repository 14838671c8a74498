"""``epos-link --help`` lists every command with one line and one example."""
from __future__ import annotations

import subprocess
import sys

from epos_link.cli import COMMANDS


def test_help_lists_every_command_with_an_example() -> None:
    p = subprocess.run([sys.executable, "-m", "epos_link.cli", "--help"], capture_output=True, text=True, timeout=60)
    assert p.returncode == 0
    lines = p.stdout.splitlines()
    for name, (_, help_text, example) in COMMANDS.items():
        at = next(i for i, line in enumerate(lines) if line.split()[:1] == [name] and help_text in line)
        assert lines[at + 1].strip() == f"e.g. {example}"
    assert "==SUPPRESS==" not in p.stdout
    assert {"monitor", "export", "wireshark", "backup", "restore", "scan", "decode"} <= set(COMMANDS)
