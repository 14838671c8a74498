#!/usr/bin/env python3
"""One entry point that sets itself up: ``python3 dev.py start`` or ``python3 dev.py test``.

It creates ``.venv`` beside this file on first use (and again whenever
pyproject.toml changes), installs the project with its test, plot, ethercat and epics extras
(and the EPICS clients its tests drive), then runs
the chosen job inside that environment. Only python3 is needed.

``start`` runs ``tcp-bridge serve`` with the arguments given: on the embedded
simulator, unless they name an axis table (``--config FILE``). Ctrl-C or
SIGTERM is forwarded to the bridge once and its clean exit awaited (it
finishes the transfers in flight); its exit status is this script's.
"""
from __future__ import annotations

import hashlib
import os
import signal
import subprocess
import sys
import venv
from pathlib import Path

ROOT = Path(__file__).resolve().parent
VENV = ROOT / ".venv"
BIN = VENV / ("Scripts" if os.name == "nt" else "bin")
PY = BIN / ("python.exe" if os.name == "nt" else "python")
STAMP = VENV / ".installed"


def ensure_env() -> None:
    want = hashlib.sha256((ROOT / "pyproject.toml").read_bytes()).hexdigest()
    if STAMP.exists() and STAMP.read_text() == want and PY.exists():
        return
    if not PY.exists():
        print("dev.py: creating .venv", flush=True)
        venv.EnvBuilder(with_pip=True).create(VENV)
    print("dev.py: installing the project and its test, plot, ethercat and epics extras into .venv",
          flush=True)
    pip = [str(PY), "-m", "pip", "install", "--disable-pip-version-check", "-q"]
    # plot, ethercat, epics (+ the CA clients pyepics, ophyd, ophyd-async): their tests
    subprocess.run(pip + ["-e", f"{ROOT}[test,plot,ethercat,epics,epics-clients]"], check=True)
    STAMP.write_text(want)


def run_tests(args: list[str]) -> int:
    """The whole suite (no arguments: mypy over both packages first, as CI runs it),
    or pytest with the arguments given (``-k framing -x``: pytest only)."""
    if not args:
        print("dev.py: mypy (the [tool.mypy] section of pyproject.toml)", flush=True)
        rc = subprocess.call([str(PY), "-m", "mypy"], cwd=ROOT)
        if rc != 0:
            print("dev.py: mypy found errors; failing", file=sys.stderr)
            return rc
    rc = subprocess.call([str(PY), "-m", "pytest", *args], cwd=ROOT)
    if rc == 5:  # pytest: no tests collected, which must never count as a pass
        print("dev.py: pytest collected no tests; failing", file=sys.stderr)
        return 1
    return rc


def bridge_command(args: list[str]) -> list[str]:
    """``tcp-bridge serve`` with the user's arguments; ``--simulate`` only when they
    name no source of axes (``--config FILE`` or ``--simulate`` themselves)."""
    cmd = [str(BIN / "tcp-bridge"), "serve"]
    sources = {"--config", "--simulate"}
    if not any(a in sources or a.startswith("--config=") for a in args):
        cmd.append("--simulate")
    return cmd + args


# After the first forwarded signal the bridge finishes the transfers in flight
# (each bounded by its own timeouts); if it is still running after this long, a
# second signal makes it exit at once, and SIGKILL follows as a last resort.
SHUTDOWN_GRACE = 60.0
SECOND_SIGNAL_GRACE = 10.0


def run_bridge(cmd: list[str]) -> int:
    """Run the bridge; Ctrl-C and SIGTERM reach it once, then its clean exit is awaited.

    The bridge runs in its own process group, so the terminal's Ctrl-C reaches
    only this script, which forwards it: the bridge sees exactly one signal and
    shuts down cleanly (a second one would make it exit at once). A second
    Ctrl-C here is forwarded too, for a user who does not want to wait.
    """
    if os.name == "nt":  # pragma: no cover - no process groups; the console signals both
        return subprocess.call(cmd, cwd=ROOT)
    child = subprocess.Popen(cmd, cwd=ROOT, start_new_session=True)
    received: list[int] = []

    def forward(signum: int, _frame: object) -> None:
        received.append(signum)
        if child.poll() is None:
            child.send_signal(signum)

    previous = {sig: signal.signal(sig, forward) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        while True:
            try:
                rc = child.wait(timeout=SHUTDOWN_GRACE if received else None)
                break
            except subprocess.TimeoutExpired:
                print("dev.py: the bridge is still shutting down; sending a second signal",
                      file=sys.stderr, flush=True)
                child.send_signal(signal.SIGTERM)
                try:
                    rc = child.wait(timeout=SECOND_SIGNAL_GRACE)
                except subprocess.TimeoutExpired:
                    child.kill()
                    rc = child.wait(timeout=SECOND_SIGNAL_GRACE)
                break
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return 128 - rc if rc < 0 else rc  # killed by signal N: the shell's 128 + N


def main() -> int:
    jobs = {"start", "test", "shell"}
    if len(sys.argv) < 2 or sys.argv[1] not in jobs:
        print("usage: python3 dev.py start [tcp-bridge serve options] | test [pytest options]",
              file=sys.stderr)
        return 2
    job, rest = sys.argv[1], sys.argv[2:]
    ensure_env()
    if job == "test":
        return run_tests(rest)
    if job == "shell":
        return subprocess.call([str(PY), *rest], cwd=ROOT)
    # The main job: the PSI TCP bridge, on the embedded simulator unless the
    # arguments name an axis table (python3 dev.py start --config axes.toml).
    return run_bridge(bridge_command(rest))


if __name__ == "__main__":
    sys.exit(main())
