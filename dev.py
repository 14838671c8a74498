#!/usr/bin/env python3
"""One entry point that sets itself up: ``python3 dev.py start`` or ``python3 dev.py test``.

It creates ``.venv`` beside this file on first use, installs into it what the chosen
job needs, then runs the job inside that environment. Only python3 is needed.

* ``start`` installs only what the bridge needs (the project and its five
  dependencies; the ``ethercat`` extra too when the arguments ask for ``--ethercat``),
  with pip's own progress shown: a first start is a minute or two, not the whole
  test tool chain (issue 34 item 6).
* ``test`` and ``shell`` install the rest: the ``test``, ``plot``, ``ethercat`` and
  ``epics`` extras (and ``epics-clients``, the EPICS clients its tests drive); ``test`` also installs, where it can (root and apt-get), the tools whose
  tests otherwise skip: tshark, tmux, chromium, iproute2 (as ``.ci/run`` did).
* ``.venv/.installed`` (the stamp) records the pyproject.toml it was installed
  from and the extras installed; a job whose extras are all there starts at once,
  a changed pyproject.toml reinstalls what was there plus what the job needs.

``start`` runs ``tcp-bridge serve`` with the arguments given: on the embedded
simulator, unless they name an axis table (``--config FILE``). Ctrl-C or
SIGTERM is forwarded to the bridge once and its clean exit awaited (it
finishes the transfers in flight); its exit status is this script's.
"""
from __future__ import annotations

import hashlib
import os
import shutil
import signal
import subprocess
import sys
import venv
from pathlib import Path
from typing import Any, Callable

ROOT = Path(__file__).resolve().parent
VENV = ROOT / ".venv"
BIN = VENV / ("Scripts" if os.name == "nt" else "bin")
PY = BIN / ("python.exe" if os.name == "nt" else "python")
STAMP = VENV / ".installed"


ALL_EXTRAS = ("test", "plot", "ethercat", "epics", "epics-clients")  # the whole suite's
# The tools some tests need; without them those tests skip and say why (.ci/run, issue 11,
# 25, 26): the command each is found by, and its Debian package.
TOOLS = {"tshark": "tshark", "tmux": "tmux", "chromium": "chromium", "ip": "iproute2"}
APT_TIMEOUT = 900  # seconds for one apt-get run (a slow mirror; never for ever)


def pyproject_hash() -> str:
    return hashlib.sha256((ROOT / "pyproject.toml").read_bytes()).hexdigest()


def stamp_extras(stamp_text: str) -> "set[str]":
    """The extras a stamp lists: ``HASH`` then ``extras: a,b`` on a second line; a
    stamp of one line is the older dev.py's, which installed all of :data:`ALL_EXTRAS`."""
    lines = stamp_text.splitlines()
    if len(lines) == 1:
        return set(ALL_EXTRAS)
    listed = lines[1].partition("extras:")[2] if len(lines) > 1 else ""
    return {e.strip() for e in listed.split(",") if e.strip()}


def installed_extras(stamp_text: str, want_hash: str) -> "set[str] | None":
    """The extras installed from this pyproject.toml, None if the stamp is for another."""
    lines = stamp_text.splitlines()
    if not lines or lines[0].strip() != want_hash:
        return None
    return stamp_extras(stamp_text)


def ensure_env(extras: "tuple[str, ...]" = ALL_EXTRAS, quiet: bool = True) -> None:
    """.venv with the project and ``extras`` installed (see the module docstring)."""
    want = pyproject_hash()
    stamp = STAMP.read_text() if STAMP.exists() and PY.exists() else ""
    have = installed_extras(stamp, want)
    if have is not None and set(extras) <= have:
        return
    if not PY.exists():
        print("dev.py: creating .venv", flush=True)
        venv.EnvBuilder(with_pip=True).create(VENV)
    # Keep what an earlier job installed: a start after a test run must not drop mypy.
    keep = sorted(set(extras) | (stamp_extras(stamp) if stamp else set()))
    what = f"and its {', '.join(keep)} extras" if keep else "and what the bridge needs"
    print(f"dev.py: installing the project {what} into .venv"
          + ("" if quiet else " (pip's progress below)"), flush=True)
    pip = [str(PY), "-m", "pip", "install", "--disable-pip-version-check"]
    if quiet:
        pip.append("-q")
    target = f"{ROOT}[{','.join(keep)}]" if keep else str(ROOT)
    subprocess.run(pip + ["-e", target], check=True)
    STAMP.write_text(f"{want}\nextras: {','.join(keep)}\n")


def missing_tools() -> "list[str]":
    return [package for command, package in TOOLS.items() if shutil.which(command) is None]


def ensure_tools(run: "Callable[..., Any]" = subprocess.run) -> "list[str]":
    """Install the missing :data:`TOOLS` with apt-get where we may (root); returns the
    packages still missing. Never fails: their tests skip and say why."""
    missing = missing_tools()
    if not missing:
        return []
    geteuid = getattr(os, "geteuid", None)
    if geteuid is None or geteuid() != 0 or shutil.which("apt-get") is None:
        print(f"dev.py: {', '.join(missing)} not installed; the tests that need them will "
              f"skip (as root: apt-get install {' '.join(missing)})", flush=True)
        return missing
    print(f"dev.py: installing {', '.join(missing)} with apt-get for the tests that need "
          "them", flush=True)
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    apt = ["apt-get", "-o", "DPkg::Lock::Timeout=300"]
    install = apt + ["install", "-y", "-q", "--no-install-recommends", *missing]
    quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL, "env": env,
             "timeout": APT_TIMEOUT}
    try:
        if run(install, **quiet).returncode != 0:  # an old package list: update, once
            run(apt + ["update", "-q"], **quiet)
            run(install, **quiet)
    except (OSError, subprocess.SubprocessError):
        pass
    still = missing_tools()
    if still:
        print(f"dev.py: could not install {', '.join(still)}; those tests will skip",
              flush=True)
    return still


# Issue 32: the whole suite runs on this many pytest-xdist workers. Most of a test's time
# is waiting (for a subprocess, a socket, a drive's ramp), so it takes more workers than
# cores to keep two cores busy; tests that must not run together share a worker
# (tests/conftest.py: groups). On this 2-core machine, quiet, warm clone, 2026-11-29:
# four 292.2 s and 295.8 s of pytest (1.64 cores busy), five 281.0 s; six were no faster
# than four (290.7 s) for 60 s more CPU.
WORKERS = 5


def test_env() -> dict[str, str]:
    """The environment of the test run: Python's bytecode cache on.

    Without it (PYTHONDONTWRITEBYTECODE set, as on some machines) every run compiles
    every test module again for pytest's assertion rewriting, and every epos-link and
    tcp-bridge the tests spawn compiles both packages again: 38 s to collect for
    ``-k framing`` on a loaded machine, and ~0.25 s of CPU per spawned command. The
    project's and the tests' bytecode goes to their __pycache__ (ignored by git); the
    standard library and .venv use the bytecode their installers wrote. (A
    PYTHONPYCACHEPREFIX, tried first, hid that bytecode: a fresh clone's suite compiled
    44 MB of the venv's and the standard library's modules into it, many processes at
    once, and its pytest took 311-317 s where a warm one took 274-296 s.)"""
    return {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}


def run_tests(args: list[str]) -> int:
    """The whole suite (no arguments: mypy over both packages first, as CI runs it, then
    every test, the slow ones included, on WORKERS xdist workers), or pytest with the
    arguments given (``-k framing -x``: pytest only, in one process)."""
    env = test_env()
    if not args:
        print("dev.py: mypy (the [tool.mypy] section of pyproject.toml)", flush=True)
        rc = subprocess.call([str(PY), "-m", "mypy"], cwd=ROOT, env=env)
        if rc != 0:
            print("dev.py: mypy found errors; failing", file=sys.stderr)
            return rc
        args = ["-n", str(WORKERS), "--dist", "loadgroup"]
    rc = subprocess.call([str(PY), "-m", "pytest", *args], cwd=ROOT, env=env)
    if rc == 5:  # pytest: no tests collected, which must never count as a pass
        print("dev.py: pytest collected no tests; failing", file=sys.stderr)
        return 1
    return rc


def start_extras(args: list[str]) -> "tuple[str, ...]":
    """What ``start`` installs beyond the bridge itself: pysoem for ``--ethercat``."""
    return ("ethercat",) if any(a == "--ethercat" or a.startswith("--ethercat=")
                                for a in args) else ()


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
    if job == "start":
        ensure_env(start_extras(rest), quiet=False)
    else:
        ensure_env()
    if job == "test":
        ensure_tools()
        return run_tests(rest)
    if job == "shell":
        return subprocess.call([str(PY), *rest], cwd=ROOT)
    # The main job: the PSI TCP bridge, on the embedded simulator unless the
    # arguments name an axis table (python3 dev.py start --config axes.toml).
    return run_bridge(bridge_command(rest))


if __name__ == "__main__":
    sys.exit(main())
