"""A veth pair for EtherCAT tests, and why there is none (shared by the simulator's and
the bridge's EtherCAT tests).

``veth_pair()`` creates ``ecA<pid>``/``ecB<pid>`` (the brief's ecatA/ecatB, made
unique per process so parallel test runs on one machine do not collide), sets both
up and deletes them afterwards; ``unavailable_reason()`` says why EtherCAT tests
must skip: not root, no ``ip`` (iproute2), no veth support, no pysoem.
"""
from __future__ import annotations

import contextlib
import importlib.util
import os
import shutil
import subprocess
from typing import Iterator, Optional


def unavailable_reason(need_pysoem: bool = True) -> Optional[str]:
    if os.geteuid() != 0:
        return "EtherCAT tests need root (a veth pair and raw packet sockets); not root"
    if shutil.which("ip") is None:
        return "EtherCAT tests need iproute2's 'ip' to create a veth pair; not installed"
    if need_pysoem and importlib.util.find_spec("pysoem") is None:
        return "EtherCAT tests need pysoem (the SOEM master); not installed"
    return None


def _ip(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True, timeout=30)


@contextlib.contextmanager
def veth_pair() -> Iterator[tuple[str, str]]:
    """(master end, slave end), both up; raises RuntimeError with ip's words if impossible."""
    a, b = f"ecA{os.getpid()}"[:15], f"ecB{os.getpid()}"[:15]
    _ip("link", "del", a)  # a leftover of a killed run of this pid
    made = _ip("link", "add", a, "type", "veth", "peer", "name", b)
    if made.returncode != 0:
        raise RuntimeError(f"no veth pair: ip link add: {made.stderr.strip()}")
    try:
        for name in (a, b):
            up = _ip("link", "set", name, "up")
            if up.returncode != 0:
                raise RuntimeError(f"ip link set {name} up: {up.stderr.strip()}")
        yield a, b
    finally:
        _ip("link", "del", a)  # deletes the peer too


def bus_open(log_text: str) -> bool:
    """A bridge's log shows its EtherCAT bus open: it was opened at start-up, or its
    probes opened it later (a loaded machine: the slaves did not answer the first time;
    tcp_bridge.backends.reopen logs "bus NAME: opened")."""
    return "opened again in the background" not in log_text or ": opened" in log_text
