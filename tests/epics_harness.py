"""Running the bridge's Channel Access server and CA clients from PyPI, each in its own
process, on loopback with a port of their own (issue 33).

* :func:`ca_env`: the environment of one test's server and clients: a free CA server
  port, searches to 127.0.0.1 only (``EPICS_CA_AUTO_ADDR_LIST=NO``), a repeater/beacon
  port of its own: parallel runs never see each other's records.
* :class:`Served`: ``tcp-bridge serve ... --epics PREFIX`` as a subprocess, with the
  PSI address it printed.
* :func:`run_client`: a client script (pyepics, ophyd, ophyd-async) in its own Python
  process; it prints one JSON object, which is returned.
* :class:`Console`: a pyepics process that takes commands on stdin (get, put, a put
  with callback that does not block and whether it completed, monitor events), for
  tests that interleave a CA client with a PSI client.

Skips: :data:`NO_SERVER` (caproto missing: the [epics] extra) and :func:`no_client`
(a client library missing: the epics-clients extra), each with the reason shown.
"""
from __future__ import annotations

import importlib
import importlib.util
import json
import os
import re
import signal
import socket
import subprocess
import sys
import textwrap
import threading
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence

ROOT = Path(__file__).resolve().parent.parent
def _importable(module: str) -> bool:
    try:
        importlib.import_module(module)
    except ImportError:
        return False
    return True


NO_SERVER: Optional[str] = None if _importable("caproto") else (
    "caproto is not installed, so serve --epics cannot run: the EPICS tests need the "
    "[epics] extra (pip install -e '.[epics]'; python3 dev.py installs it)")


def no_client(module: str) -> Optional[str]:
    """Why a CA client library cannot be used here, or None."""
    if NO_SERVER:
        return NO_SERVER
    if importlib.util.find_spec(module) is None:  # not imported here: libca loads on import
        return (f"{module} is not installed: the EPICS client tests need the epics-clients "
                "extra (pip install -e '.[epics-clients]'; python3 dev.py installs it)")
    return None


def free_port() -> int:
    """A port free for both TCP and UDP on 127.0.0.1 (CA uses the same number for both)."""
    for _ in range(50):
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as tcp:
            tcp.bind(("127.0.0.1", 0))
            port = tcp.getsockname()[1]
        try:
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
                udp.bind(("127.0.0.1", port))
        except OSError:
            continue
        return int(port)
    raise RuntimeError("no free port")


def ca_env() -> Dict[str, str]:
    env = dict(os.environ)
    port, repeater = free_port(), free_port()
    env.update(EPICS_CA_SERVER_PORT=str(port), EPICS_CA_ADDR_LIST="127.0.0.1",
               EPICS_CA_AUTO_ADDR_LIST="NO", EPICS_CA_REPEATER_PORT=str(repeater),
               EPICS_CAS_BEACON_PORT=str(repeater), EPICS_CAS_INTF_ADDR_LIST="127.0.0.1",
               PYTHONPATH=str(ROOT), PYTHONUNBUFFERED="1")
    for key in ("EPICS_CAS_BEACON_ADDR_LIST",):
        env.pop(key, None)
    return env


class Served:
    """``tcp-bridge serve <args> --epics PREFIX`` in a subprocess (stopped by close())."""

    def __init__(self, args: Sequence[str], prefix: str = "TST:",
                 env: Optional[Dict[str, str]] = None) -> None:
        self.env = env or ca_env()
        self.prefix = prefix
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "tcp_bridge.cli", "serve", *args, "--port", "0",
             "--maintenance-port", "-1", "--epics", prefix],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=self.env,
            cwd=ROOT)
        self.lines: List[str] = []
        self.psi = ""
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.append(line)
            m = re.search(r"listening on (\S+) \(NICOS", line)
            self.psi = m.group(1) if m else self.psi
            if "EPICS Channel Access on" in line or self.proc.poll() is not None:
                break
        assert self.psi and "EPICS Channel Access on" in self.lines[-1], "".join(self.lines)
        self.output: List[str] = []  # what it printed since it started, as it comes
        # Drained as it comes: a bridge run with -v must never block on a full pipe.
        self._reader = threading.Thread(target=self._drain, daemon=True)
        self._reader.start()

    def _drain(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.output.append(line)

    def close(self) -> str:
        """Stop the bridge (SIGINT, its clean exit); what it printed after it started."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
        try:
            self.proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(timeout=10)
        self._reader.join(10)
        return "".join(self.output)


def run_client(script: str, env: Dict[str, str], timeout: float = 180.0) -> Dict[str, Any]:
    """Run ``script`` (dedented) in its own Python; the JSON object it printed last."""
    proc = subprocess.run([sys.executable, "-c", textwrap.dedent(script)], env=env,
                          capture_output=True, text=True, timeout=timeout, cwd=ROOT)
    lines = [line for line in proc.stdout.splitlines() if line.startswith("{")]
    assert proc.returncode == 0 and lines, proc.stdout + proc.stderr
    result: Dict[str, Any] = json.loads(lines[-1])
    return result


CONSOLE = """
import json, sys, time, epics
events = {}
def on_change(pvname=None, value=None, **kw):
    events.setdefault(pvname, []).append(value)
pvs = {}
for line in sys.stdin:
    cmd = json.loads(line)
    op = cmd["op"]
    try:
        if op == "get":
            out = epics.caget(cmd["pv"], as_string=cmd.get("as_string", False),
                              use_monitor=False, timeout=10)
        elif op == "put":
            out = epics.caput(cmd["pv"], cmd["value"], wait=cmd.get("wait", False),
                              timeout=cmd.get("timeout", 60))
        elif op == "put_async":  # a put with callback that does not block the console
            pv = pvs.get(cmd["pv"]) or epics.PV(cmd["pv"])
            pv.wait_for_connection(10)
            pvs[cmd["pv"]] = pv
            pv.put(cmd["value"], wait=False, use_complete=True)
            out = True
        elif op == "complete":  # whether the last put_async of the PV has completed
            out = bool(pvs[cmd["pv"]].put_complete)
        elif op == "monitor":
            pv = epics.PV(cmd["pv"], callback=on_change, auto_monitor=True)
            pv.wait_for_connection(10)
            pvs[cmd["pv"]] = pv
            out = True
        elif op == "events":
            out = events.get(cmd["pv"], [])
        elif op == "severity":
            pv = epics.PV(cmd["pv"], form="time")
            pv.wait_for_connection(10)
            pv.get_with_metadata(use_monitor=False, form="time")
            out = [pv.status, pv.severity]
        else:
            out = "unknown op"
    except Exception as exc:
        out = {"error": repr(exc)}
    if hasattr(out, "tolist"):
        out = out.tolist()
    print(json.dumps(out), flush=True)
"""


class Console:
    """A pyepics client process that answers one JSON line per command."""

    def __init__(self, env: Dict[str, str]) -> None:
        self.proc = subprocess.Popen([sys.executable, "-c", CONSOLE], env=env, cwd=ROOT,
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     stderr=subprocess.DEVNULL, text=True)

    def __call__(self, op: str, pv: str, **kw: Any) -> Any:
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self.proc.stdin.write(json.dumps({"op": op, "pv": pv, **kw}) + "\n")
        self.proc.stdin.flush()
        line = self.proc.stdout.readline()
        assert line, "the CA client process ended"
        return json.loads(line)

    def close(self) -> None:
        if self.proc.stdin is not None:
            self.proc.stdin.close()
        try:
            self.proc.wait(15)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(5)
