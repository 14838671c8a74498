"""The soak, 20 seconds of it (issue 12): 16 clients poll and move 8 simulated axes through a
``tcp-bridge serve --simulate`` process; nothing is lost, no move runs twice or ends
elsewhere, and the server's memory and descriptors come back to where they started.

The full run is ``python bench/soak.py`` (600 s); its figures are in docs/benchmarks.md.
"""
from __future__ import annotations

import importlib.util
import os
import sys
from pathlib import Path
from types import ModuleType

import pytest

pytestmark = pytest.mark.skipif(not os.path.isdir("/proc/self/fd"),
                                reason="the soak reads the server's RSS and descriptors in /proc")

RSS_TOLERANCE = 16 * 2**20  # bytes: the interpreter's allocator may keep what it used


def soak_module() -> ModuleType:
    path = Path(__file__).resolve().parent.parent / "bench" / "soak.py"
    spec = importlib.util.spec_from_file_location("bench_soak", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def test_twenty_second_soak_loses_nothing_and_leaks_nothing() -> None:
    soak = soak_module()
    report = soak.run(clients=16, axes=8, duration=20.0)
    text = "\n".join(report.lines())
    print("\n" + text)
    tally = report.tally
    assert tally.errors == {}, text  # nothing lost, refused or mismatched
    assert tally.moves_started > 0 and tally.moves_exact == tally.moves_started, text
    assert tally.requests > 1000, text
    # Descriptors: one per connection while they are open, none left after they close.
    assert report.fds["end"] == report.fds["start"], text
    assert report.fds["after"] == report.fds["before"], text
    # Memory: flat while serving, back near where it was once the clients left.
    assert report.rss["end"] - report.rss["start"] < RSS_TOLERANCE, text
    assert report.rss["after"] - report.rss["before"] < RSS_TOLERANCE, text
    assert report.server_exit == 0 and "Traceback" not in report.server_log, text
