#!/usr/bin/env python3
"""One entry point that sets itself up: ``python3 dev.py start`` or ``python3 dev.py test``.

It creates ``.venv`` beside this file on first use (and again whenever
pyproject.toml changes), installs the project with its test extra, then runs
the chosen job inside that environment. Only python3 is needed.
"""
from __future__ import annotations

import hashlib
import os
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
    print("dev.py: installing the project and its test extra into .venv", flush=True)
    pip = [str(PY), "-m", "pip", "install", "--disable-pip-version-check", "-q"]
    subprocess.run(pip + ["-e", f"{ROOT}[test]"], check=True)
    STAMP.write_text(want)


def run_tests(args: list[str]) -> int:
    rc = subprocess.call([str(PY), "-m", "pytest", *args], cwd=ROOT)
    if rc == 5:  # pytest: no tests collected, which must never count as a pass
        print("dev.py: pytest collected no tests; failing", file=sys.stderr)
        return 1
    return rc


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
    # The main job: the PSI TCP bridge on the embedded simulator (issue 6).
    cmd = [str(BIN / "tcp-bridge"), "serve", "--simulate", *rest]
    try:
        return subprocess.call(cmd, cwd=ROOT)
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
