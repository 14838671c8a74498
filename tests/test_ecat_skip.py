"""Without root, iproute2, veth or pysoem the EtherCAT tests skip and say why (issue 26,
"must show" 4); the CLI refuses clearly, exit 2, without CAP_NET_RAW or an interface."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests import ecat_veth

ROOT = Path(__file__).resolve().parent.parent


def test_not_root_is_named(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(os, "geteuid", lambda: 1000)
    assert "not root" in (ecat_veth.unavailable_reason() or "")


def test_no_iproute2_is_named(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(os, "geteuid", lambda: 0)
    monkeypatch.setattr(shutil, "which", lambda name: None)
    assert "iproute2" in (ecat_veth.unavailable_reason() or "")


def test_no_veth_support_is_named(monkeypatch: pytest.MonkeyPatch) -> None:
    failed = subprocess.CompletedProcess([], 2, "", "Error: Unknown device type.")
    monkeypatch.setattr(ecat_veth, "_ip", lambda *args: failed)
    with pytest.raises(RuntimeError, match="no veth pair: ip link add: Error: Unknown device type"):
        with ecat_veth.veth_pair():
            pass


def test_the_integration_test_skips_visibly_when_not_root() -> None:
    if os.geteuid() != 0 or shutil.which("setpriv") is None:
        pytest.skip("needs root and setpriv to run pytest as another user")
    out = subprocess.run(["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups",
                          sys.executable, "-m", "pytest", "-q", "-rs", "-p", "no:cacheprovider",
                          "tests/test_ecat_pysoem.py"], cwd=ROOT, capture_output=True, text=True,
                         timeout=300, env={**os.environ, "HOME": "/tmp"})
    if "Permission denied" in out.stdout + out.stderr and "skipped" not in out.stdout:
        pytest.skip("user nobody cannot read this worktree")
    assert "1 skipped" in out.stdout, out.stdout + out.stderr
    assert "EtherCAT tests need root" in out.stdout


def test_cli_without_an_interface_exits_2_with_one_line() -> None:
    out = subprocess.run([sys.executable, "-m", "epos_link.cli", "sim", "--ethercat", "nosuchif9"],
                         cwd=ROOT, capture_output=True, text=True, timeout=120)
    if os.geteuid() != 0:
        assert out.returncode == 2 and "needs root or CAP_NET_RAW" in out.stderr
    else:
        assert out.returncode == 2
        assert out.stderr.strip() == "epos-link sim: cannot serve EtherCAT on 'nosuchif9': No such device"


def test_cli_without_cap_net_raw_exits_2_with_one_line() -> None:
    if os.geteuid() == 0 and shutil.which("setpriv") is None:
        pytest.skip("root without setpriv cannot drop CAP_NET_RAW here")
    prefix = (["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups"]
              if os.geteuid() == 0 else [])
    out = subprocess.run([*prefix, sys.executable, "-m", "epos_link.cli", "sim", "--ethercat", "lo"],
                         cwd=ROOT, capture_output=True, text=True, timeout=120,
                         env={**os.environ, "HOME": "/tmp"})
    if "Permission denied" in out.stderr and "CAP_NET_RAW" not in out.stderr:
        pytest.skip("user nobody cannot read this worktree")
    assert out.returncode == 2
    assert out.stderr.strip() == ("epos-link sim: --ethercat lo needs root or CAP_NET_RAW "
                                  "(a raw packet socket)")
