"""Durable before ACK (issue 35): the state file holds an ACK'd value before the ACK
leaves, even across ``kill -9``, and a killed writer's temporaries are cleaned at start.

The full run of the kill trials is ``python bench/killed_writes.py`` (30 trials).
"""
from __future__ import annotations

import importlib.util
import os
import stat
import sys
from pathlib import Path
from types import ModuleType
from typing import Any, List, Tuple

import pytest

from tcp_bridge.tables.axes import AxisTable, ConfigError
from tcp_bridge.tables.parameters import ParameterStore
from tcp_bridge.tables.statefile import remove_stale_temporaries, write_atomically


def table() -> AxisTable:
    return AxisTable.from_mapping({"bus": {"can1": {"backend": "instant"}},
                                   "axis": [{"node_id": 1, "position_factor": 1000}]})


def killed_writes() -> ModuleType:
    path = Path(__file__).resolve().parent.parent / "bench" / "killed_writes.py"
    spec = importlib.util.spec_from_file_location("bench_killed_writes", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def test_kill_9_during_back_to_back_acked_writes_loses_no_acked_value() -> None:
    """Three trials of the bench (30 there): a bridge killed at a random instant
    restarts with the last ACK'd value, or the write in flight, and no temporary."""
    bench = killed_writes()
    lines: List[str] = []
    results = bench.run(trials=3, seed=35, out=lines)
    text = "\n".join(lines)
    assert all(t.acked > 1 for t in results), text  # the kill came during the writes
    assert [t.verdict for t in results if t.verdict not in ("last ACK'd", "in flight")] == [], text
    assert [t.temporaries_after for t in results] == [[], [], []], text


def test_stale_temporaries_are_removed_at_start(tmp_path: Path) -> None:
    path = tmp_path / "s.json"
    write_atomically(path, '{"format": "tcp-bridge-state", "version": 1, "axes": {}}\n')
    stale = [tmp_path / ".s.json.k2j4d9xq.tmp", tmp_path / ".s.json.a.tmp"]
    others = [tmp_path / ".other.json.k2j4d9xq.tmp", tmp_path / "s.json.tmp",
              tmp_path / ".s.json.tmp"]  # another file's temporary; not ours
    for p in stale + others:
        p.write_text("{")
    ParameterStore(table(), path)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        ["s.json", *(p.name for p in others)])


def test_a_read_only_store_leaves_a_running_bridges_temporaries(tmp_path: Path) -> None:
    # `tcp-bridge check` beside a running bridge: its temporary may be a write in progress.
    path = tmp_path / "s.json"
    busy = tmp_path / ".s.json.inprogress.tmp"
    busy.write_text("{")
    ParameterStore(table(), path, read_only=True)
    assert busy.exists()
    assert remove_stale_temporaries(path) == [busy] and not busy.exists()


def test_the_rename_is_made_durable_by_an_fsync_of_the_directory(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """fsync(2): the file's fsync does not make its directory entry durable; the
    directory must be fsynced after the rename."""
    events: List[Tuple[str, Any]] = []
    real_fsync, real_replace = os.fsync, os.replace

    def fsync(fd: int) -> None:
        events.append(("fsync", "dir" if stat.S_ISDIR(os.fstat(fd).st_mode) else "file"))
        real_fsync(fd)

    def replace(src: Any, dst: Any) -> None:
        events.append(("replace", Path(dst).name))
        real_replace(src, dst)
    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setattr(os, "replace", replace)
    write_atomically(tmp_path / "s.json", "{}\n")
    assert events == [("fsync", "file"), ("replace", "s.json"), ("fsync", "dir")]


def test_waiters_are_released_when_their_write_ends_even_if_it_fails(tmp_path: Path) -> None:
    import asyncio

    blocker = tmp_path / "gone"
    store = ParameterStore(table(), blocker / "s.json")
    blocker.rmdir()  # made by the start-up check ...
    blocker.write_text("x")  # ... then the directory cannot be created: writes fail

    async def go() -> bool:
        store.set(1, 22, -1)
        return await store.written(store.version, 30.0)
    assert asyncio.run(go())  # ended (failed and logged), not waiting for ever
    store.close()


def test_a_state_file_nested_2000_deep_is_one_clear_line(tmp_path: Path) -> None:
    """Issue 35: json recurses per bracket; 2,000 of them were a RecursionError traceback."""
    path = tmp_path / "s.json"
    path.write_text("[" * 2000 + "]" * 2000)
    with pytest.raises(ConfigError) as info:
        ParameterStore(table(), path)
    assert str(info.value) == (f"state file {path} is damaged (nested too deeply to be a "
                               "state file); move it away to start from the axis table")


def test_serve_with_a_deeply_nested_state_file_is_one_line_and_exit_2(tmp_path: Path) -> None:
    import subprocess

    path = tmp_path / "s.json"
    path.write_text('{"a": ' * 2000 + "1" + "}" * 2000)
    proc = subprocess.run([sys.executable, "-m", "tcp_bridge.cli", "serve", "--simulate",
                           "--state-file", str(path), "--port", "0", "--maintenance-port", "-1"],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    assert proc.stderr.splitlines() == [
        f"tcp-bridge: state file {path} is damaged (nested too deeply to be a state file); "
        "move it away to start from the axis table"]
