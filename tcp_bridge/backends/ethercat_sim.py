"""``tcp-bridge serve --simulate --ethercat N``: N simulated EPOS4 EtherCAT slaves on a veth pair.

The simulated slaves (:mod:`epos_link.simulator.ethercat`) answer raw Ethernet
frames on a network interface; the ``ethercat`` backend (pysoem, SOEM) sends
them on another. A veth pair joins the two: ``tbm<pid>`` is the master's end,
``tbs<pid>`` the slaves' end (unique per process, so two bridges on one machine
do not collide; at most 15 characters, the kernel's IFNAMSIZ - 1).

The slaves run in a **child process** (``epos-link sim --ethercat tbs<pid>
--slaves N``), not a thread: pysoem holds the GIL during its SOEM calls, so
slaves in the bridge's own process would miss the frames the master is
waiting for. The child gets its own session, so a terminal's Ctrl-C reaches
only the bridge, which stops its axes first and the slaves after; and
``PR_SET_PDEATHSIG`` (Linux prctl(2)) ends it if the bridge dies without
cleaning up. :meth:`SimulatedEthercat.close` stops the child and deletes the
pair (deleting one end deletes its peer, ip-link(8)).

What the machine must allow (:func:`unavailable_reason`): root, for the veth
pair (CAP_NET_ADMIN) and raw packet sockets on both ends (CAP_NET_RAW, which
the child needs too, so file capabilities on the bridge alone would not do);
iproute2's ``ip``; pysoem.
"""
from __future__ import annotations

import ctypes
import importlib.util
import os
import select
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Optional

# The child imports epos_link and opens its socket within a second on an idle
# machine; this bound allows for a loaded one.
READY_TIMEOUT = 60.0
STOP_TIMEOUT = 10.0
MAX_SLAVES = 64  # epos_link.simulator.ethercat.server.EthercatServer's bound


def unavailable_reason() -> Optional[str]:
    """Why this machine cannot run the simulated EtherCAT slaves, or None if it can."""
    if not hasattr(os, "geteuid") or not sys.platform.startswith("linux"):
        return "needs Linux (a veth pair and raw packet sockets)"
    if os.geteuid() != 0:
        return ("needs root: CAP_NET_ADMIN for the veth pair and CAP_NET_RAW for raw "
                "Ethernet frames (try sudo)")
    if shutil.which("ip") is None:
        return "needs iproute2's 'ip' to make the veth pair; not installed"
    if importlib.util.find_spec("pysoem") is None:
        return "needs pysoem, the EtherCAT master (pip install 'epos-link[ethercat]')"
    return None


def _ip(*args: str) -> "subprocess.CompletedProcess[str]":
    return subprocess.run(["ip", *args], capture_output=True, text=True, timeout=30)


def _die_with_parent() -> None:  # pragma: no cover - runs in the child, between fork and exec
    try:
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)  # 1 = PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


class SimulatedEthercat:
    """The veth pair and the child serving ``slaves`` simulated slaves; :meth:`close` undoes both.

    Raises :class:`RuntimeError` with one line saying why when either cannot be made.
    Call from the main thread: PR_SET_PDEATHSIG fires when the *thread* that
    started the child ends.
    """

    def __init__(self, slaves: int) -> None:
        if not 1 <= slaves <= MAX_SLAVES:
            raise ValueError(f"--ethercat must be 1..{MAX_SLAVES} slaves, not {slaves}")
        self.slaves = slaves
        self.interface = f"tbm{os.getpid()}"[:15]  # the master's end
        self.peer = f"tbs{os.getpid()}"[:15]  # the slaves' end
        self._child: Optional["subprocess.Popen[str]"] = None
        self._made = False
        try:
            self._make_pair()
            self._start_child()
        except BaseException:
            self.close()
            raise

    def _make_pair(self) -> None:
        _ip("link", "del", self.interface)  # the leftover of a killed bridge with this pid
        made = _ip("link", "add", self.interface, "type", "veth", "peer", "name", self.peer)
        if made.returncode != 0:
            raise RuntimeError(f"cannot make a veth pair: ip link add: {made.stderr.strip()}")
        self._made = True
        for name in (self.interface, self.peer):
            up = _ip("link", "set", "dev", name, "up")
            if up.returncode != 0:
                raise RuntimeError(f"ip link set {name} up: {up.stderr.strip()}")

    def _start_child(self) -> None:
        import epos_link

        # The child imports the same epos_link as this process (a checkout run with
        # python -m included), whatever its working directory.
        where = str(Path(epos_link.__file__).resolve().parent.parent)
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(p for p in (where, env.get("PYTHONPATH")) if p)
        self._child = subprocess.Popen(
            [sys.executable, "-m", "epos_link", "sim", "--ethercat", self.peer,
             "--slaves", str(self.slaves)],
            stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, text=True, env=env,
            start_new_session=True, preexec_fn=_die_with_parent)
        line = self._first_line(self._child, READY_TIMEOUT)
        if not line.startswith("EtherCAT:"):
            raise RuntimeError("the simulated EtherCAT slaves did not start (epos-link sim "
                               f"--ethercat {self.peer}: {line or 'no answer'})")

    @staticmethod
    def _first_line(child: "subprocess.Popen[str]", timeout: float) -> str:
        """The child's ready line ("EtherCAT: N simulated ..."), "" if it exits or is silent."""
        assert child.stdout is not None
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            ready, _, _ = select.select([child.stdout], [], [], 0.2)
            if ready:
                return child.stdout.readline().strip()
            if child.poll() is not None:
                return f"exited with status {child.returncode}"
        return ""

    @property
    def running(self) -> bool:
        return self._child is not None and self._child.poll() is None

    @property
    def pid(self) -> Optional[int]:
        return None if self._child is None else self._child.pid

    def close(self, timeout: float = STOP_TIMEOUT) -> None:
        """Stop the child (SIGTERM, then SIGKILL after ``timeout``), delete the pair. Idempotent."""
        child, self._child = self._child, None
        if child is not None:
            if child.poll() is None:
                child.terminate()
                try:
                    child.wait(timeout)
                except subprocess.TimeoutExpired:
                    child.kill()
                    child.wait(timeout)
            if child.stdout is not None:
                child.stdout.close()
        if self._made:
            self._made = False
            _ip("link", "del", self.interface)  # deletes the peer too

    def __enter__(self) -> "SimulatedEthercat":
        return self

    def __exit__(self, *_: object) -> None:
        self.close()


def start(slaves: int) -> SimulatedEthercat:
    """The pair and the child, or RuntimeError saying in one line why not (for the CLI)."""
    if not 1 <= slaves <= MAX_SLAVES:
        raise RuntimeError(f"must be 1..{MAX_SLAVES} slaves, not {slaves}")
    why = unavailable_reason()
    if why is not None:
        raise RuntimeError(why)
    try:
        return SimulatedEthercat(slaves)
    except RuntimeError as exc:
        raise RuntimeError(f"cannot start: {exc}") from None
