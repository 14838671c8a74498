"""How the suite runs (issue 32): markers, hypothesis settings, xdist groups, order.

* ``slow``: a test that keeps a wait at its real value (an idle timeout, a gateway's
  SDO timeout, a scan of every node): the one test per timeout that the faster
  tests, which shrink it, lean on. CI runs them (``dev.py test`` runs everything);
  ``-m "not slow"`` leaves them out while working.
* **hypothesis**: no per-example deadline and no "too slow" health check. Both
  measure wall-clock time, which a loaded 2-core machine stretches at random (a
  test that fails once under load is a defect, GUIDE.md); what each property
  checks is unchanged, and so is its number of examples.
* **xdist groups** (``dev.py test`` runs ``-n N --dist loadgroup``): tests that must
  not run at the same time as each other go to one worker, in order. A module is
  put in a group by what it uses, read from its source, so a new test file that
  uses a veth pair, tmux or chromium lands in the right group by itself:
  ``veth`` (root, veth pairs, raw sockets, the EtherCAT cycle: one at a time, so
  slaves' process-data watchdogs see only one master's cycle competing for the
  CPU), ``tmux`` (one tmux server for every session), ``chromium``.
* **priority**: the ``veth`` group's tests run 10 nice levels higher (as root, which
  they need anyway): the simulated EtherCAT slaves and the bridges they start inherit it. A slave
  answers a frame within microseconds; SOEM waits 10 ms for it (FRAME_TIMEOUT_US), and
  on six workers over two cores a simulated slave in a worker at the same priority as
  the rest of the suite missed 15 % of its frames ('388 with a short working counter' of
  2561 cycles) until a CoE transfer failed twice and a request was NAK. The device is
  never that late; the simulator must not be made late by our own suite.
* **order**: the groups, then the ``slow`` tests and those measured longest
  (``LONG``), then the rest, each in collection order: the long work starts first and the short tests fill in around it, so
  no worker is left with a long test at the end.
"""
from __future__ import annotations

import functools
import os
import signal
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import pytest
from hypothesis import HealthCheck, settings

settings.register_profile("suite", deadline=None, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile("suite")

# group -> words in a test module's source that put it in the group
GROUPS: Tuple[Tuple[str, Tuple[str, ...]], ...] = (
    ("veth", ("veth", "SimulatedEthercat")),
    ("tmux", ("TMUX",)),
    ("chromium", ("tests.cdp",)),
)
FIRST = [name for name, _ in GROUPS]
AHEAD = {"veth": -10}  # group -> how much higher its tests run (module docstring)
# The longest tests by --durations (each 15-65 s on this machine, waiting or computing):
# they start with the slow ones, so that no worker is left with one of them at the end.
LONG = (
    "tests/test_docs_commands.py::test_console_block[docs/epos-link.md:",  # a scan of 127 nodes
    "tests/test_bridge_profile.py::test_a_line_is_continuous",
    "tests/test_cli_sim.py::test_twenty_commands_in_a_row",
    "tests/test_soak.py::",
    "tests/test_bridge_heartbeat_e2e.py::",
    "tests/test_bridge_config.py::test_any_document",
    "tests/test_record.py::test_record_a_move_at_5_ms",
    "tests/test_docs_recording_walkthrough.py::",  # ten walkthroughs, ~50 s
)


def pytest_configure(config: pytest.Config) -> None:
    # A suite started in the background of a shell without job control (`dev.py test &`
    # in a script, nohup, some CI runners) inherits SIGINT ignored, and passes it on to
    # every process a test spawns: Python then installs no KeyboardInterrupt handler,
    # and the tests that press Ctrl-C on a command (scan, backup, can.logger, serve) saw
    # it run on. A handler of our own is reset to the default at exec, so children get
    # Ctrl-C as they would under a terminal.
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    config.addinivalue_line("markers", "slow: keeps a wait at its real value (see tests/conftest.py)")
    config.addinivalue_line("markers", "xdist_group(name): run on one worker with the rest of its group")


@functools.lru_cache(maxsize=None)
def group_of(path: Path) -> Optional[str]:
    try:
        source = path.read_text()
    except OSError:
        return None
    for name, words in GROUPS:
        if any(word in source for word in words):
            return name
    return None


# tryfirst: the markers must be in place before pytest-xdist's worker reads them in its own
# pytest_collection_modifyitems (it appends "@group" to each nodeid; --dist loadgroup
# schedules by that suffix).
@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config: pytest.Config, items: List[pytest.Item]) -> None:
    grouped: Dict[str, List[pytest.Item]] = {name: [] for name in FIRST}
    slow: List[pytest.Item] = []
    rest: List[pytest.Item] = []
    for item in items:
        group = None if item.get_closest_marker("xdist_group") else group_of(Path(item.path))
        if group is not None:
            item.add_marker(pytest.mark.xdist_group(group))
            grouped[group].append(item)
        elif item.get_closest_marker("slow") or item.nodeid.startswith(LONG):
            slow.append(item)
        else:
            rest.append(item)
    items[:] = [i for name in FIRST for i in grouped[name]] + slow + rest


def _base_nice() -> int:
    try:
        return os.getpriority(os.PRIO_PROCESS, 0)
    except (OSError, AttributeError):
        return 0


BASE_NICE = _base_nice()  # what the suite was started at (`nice dev.py test` stays nice)


def _nice(value: int) -> None:
    """The calling thread's nice value (Linux: per thread; threads and processes it
    starts inherit it). Lowering it needs root; without, the tests run as they are."""
    try:
        if os.getpriority(os.PRIO_PROCESS, 0) != value:
            os.setpriority(os.PRIO_PROCESS, 0, value)
    except (OSError, AttributeError):
        pass


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_setup(item: pytest.Item) -> None:
    """Before the test's fixtures: its group's priority (module docstring)."""
    marker = item.get_closest_marker("xdist_group")
    group = (marker.args[0] if marker.args else marker.kwargs.get("name")) if marker else None
    _nice(max(-20, BASE_NICE + AHEAD.get(str(group), 0)))


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_node_collection_finished(node: object, ids: List[str]) -> None:
    """On the xdist controller, under --dist loadgroup: the nodeid of every test of a
    group must carry its "@group" (xdist's worker appends it; the scheduler groups by
    it). If not, the groups are silently ignored (pytest 9.2 with pytest-xdist 3.8,
    pytest-dev/pytest-xdist#1386): fail the run rather than run veth tests side by side."""
    config = getattr(node, "config", None)
    if config is None or config.getoption("dist", None) != "loadgroup":
        return
    lost = [nodeid for nodeid in ids if "@" not in nodeid.rpartition("]")[2]
            and group_of(Path(__file__).parent.parent / nodeid.split("::")[0]) is not None]
    if lost:
        raise pytest.UsageError(
            f"--dist loadgroup does not group here: {lost[0]} has no @group suffix (pytest "
            f"{pytest.__version__}; see pytest-dev/pytest-xdist#1386 and pyproject.toml)")
