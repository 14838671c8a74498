"""Without the [epics] extra (issue 33, Must show 5): ``serve --epics`` is one line saying
how to install it (exit 2), and the EPICS tests skip with that reason while the rest
passes. caproto is hidden from a child Python (``sys.modules["caproto"] = None`` makes
its import fail, as on a machine without it)."""
from __future__ import annotations

import subprocess
import sys

from tests.epics_harness import ROOT, ca_env

HIDE = "import sys; sys.modules['caproto'] = None; "


def test_serve_epics_without_caproto_is_one_line_and_exit_2() -> None:
    proc = subprocess.run(
        [sys.executable, "-c", HIDE + "from tcp_bridge.cli import main; sys.exit(main())",
         "serve", "--simulate", "--port", "0", "--maintenance-port", "-1", "--epics", "X:"],
        capture_output=True, text=True, timeout=120, cwd=ROOT, env=ca_env())
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert proc.stderr.strip().splitlines() == [
        "tcp-bridge: --epics needs caproto, the optional extra [epics]: pip install "
        "'epos-link[epics]' (in a checkout: .venv/bin/pip install -e '.[epics]')"]


def test_the_epics_tests_skip_and_say_why_without_caproto() -> None:
    proc = subprocess.run(
        [sys.executable, "-c", HIDE + "import pytest; sys.exit(pytest.main(["
         "'-q', '-rs', '-p', 'no:cacheprovider', 'tests/test_epics_clients.py', "
         "'tests/test_epics_silent_bus.py']))"],
        capture_output=True, text=True, timeout=300, cwd=ROOT, env=ca_env())
    assert proc.returncode == 0, proc.stdout + proc.stderr
    skips = [line for line in proc.stdout.splitlines() if line.startswith("SKIPPED")]
    assert len(skips) == 6, proc.stdout  # every EPICS test, each with the reason
    assert all("caproto is not installed" in line and "[epics] extra" in line
               for line in skips), skips
    assert " passed" not in proc.stdout and "6 skipped" in proc.stdout, proc.stdout
