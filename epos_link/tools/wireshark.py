"""``epos-link wireshark path | install``: the MAXON SERIAL V2 dissector for Wireshark.

* ``path`` prints where the Lua dissector shipped in the package is, for
  ``wireshark -X lua_script:$(epos-link wireshark path) -r cap.pcapng``.
* ``install`` copies it into the user's personal Lua plugin folder, and writes
  an extcap entry (:mod:`epos_link.tools.extcap`) so that Wireshark lists a
  "maxon EPOS4" interface that captures live through ``epos-link monitor``.

The folders come from ``tshark -G folders`` when tshark is installed ("Personal
Lua Plugins", "Personal Extcap path"), else from Wireshark's documented
defaults (``~/.local/lib/wireshark/plugins``; ``%APPDATA%\\Wireshark\\plugins``
on Windows); ``--lua-dir`` and ``--extcap-dir`` choose others. Wireshark 4.0
reads extcap programs only from its global folder or from
``$WIRESHARK_EXTCAP_DIR`` (a personal extcap folder came with 4.2): where
tshark names no personal extcap folder, install says how to use the entry.
"""
from __future__ import annotations

import argparse
import os
import shutil
import stat
import subprocess
import sys
from importlib import resources
from pathlib import Path
from typing import Optional

DISSECTOR = "maxon_serial_v2.lua"
EXTCAP_NAME = "epos_link_extcap"


def dissector_path() -> Path:
    return Path(str(resources.files("epos_link") / "wireshark" / DISSECTOR))


def wireshark_folders(tshark: Optional[str] = None, timeout: float = 10.0) -> dict[str, str]:
    """``tshark -G folders`` as a dict ("Personal Lua Plugins" -> path); {} without tshark."""
    exe = tshark or shutil.which("tshark")
    if not exe:
        return {}
    try:
        out = subprocess.run([exe, "-G", "folders"], capture_output=True, text=True, timeout=timeout).stdout
    except (OSError, subprocess.TimeoutExpired):
        return {}
    folders: dict[str, str] = {}
    for line in out.splitlines():
        key, sep, value = line.partition(":")
        if sep and value.strip():
            folders.setdefault(key.strip(), value.strip())
    return folders


def default_lua_dir(folders: dict[str, str]) -> Path:
    if "Personal Lua Plugins" in folders:
        return Path(folders["Personal Lua Plugins"])
    if os.name == "nt":
        return Path(os.environ.get("APPDATA", Path.home())) / "Wireshark" / "plugins"
    return Path.home() / ".local" / "lib" / "wireshark" / "plugins"


def default_extcap_dir(folders: dict[str, str]) -> tuple[Path, bool]:
    """The extcap folder and whether Wireshark reads it by itself."""
    for key in ("Personal Extcap path", "Personal extcap path"):
        if key in folders:
            return Path(folders[key]), True
    if os.name == "nt":
        return Path(os.environ.get("APPDATA", Path.home())) / "Wireshark" / "extcap", False
    return Path.home() / ".local" / "lib" / "wireshark" / "extcap", False


def extcap_script() -> str:
    """The extcap entry: runs this Python with :mod:`epos_link.tools.extcap`."""
    return (f"#!{sys.executable}\n"
            "# Wireshark extcap entry installed by `epos-link wireshark install`:\n"
            "# captures live through `epos-link monitor` (see epos_link/tools/extcap.py).\n"
            "import sys\n"
            "from epos_link.tools.extcap import main\n"
            "sys.exit(main())\n")


def install_extcap(folder: Path) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    if os.name == "nt":
        target = folder / f"{EXTCAP_NAME}.bat"
        target.write_text(f'@"{sys.executable}" -m epos_link.tools.extcap %*\r\n', encoding="utf-8")
        return target
    target = folder / EXTCAP_NAME
    target.write_text(extcap_script(), encoding="utf-8")
    target.chmod(target.stat().st_mode | stat.S_IXUSR | stat.S_IXGRP | stat.S_IXOTH)
    return target


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("action", choices=["path", "install"],
                        help="path: print the dissector's path; install: copy it (and an extcap entry) "
                        "into your Wireshark folders")
    parser.add_argument("--lua-dir", type=Path, help="folder for the dissector (default: Wireshark's personal Lua plugins)")
    parser.add_argument("--extcap-dir", type=Path, help="folder for the extcap entry")
    parser.add_argument("--no-extcap", action="store_true", help="install the dissector only")


def run(args: argparse.Namespace) -> int:
    prog = "epos-link wireshark"
    source = dissector_path()
    if args.action == "path":
        print(source)
        return 0
    folders = wireshark_folders() if not (args.lua_dir and (args.extcap_dir or args.no_extcap)) else {}
    lua_dir = args.lua_dir or default_lua_dir(folders)
    try:
        lua_dir.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(source, lua_dir / DISSECTOR)
        print(f"dissector: {lua_dir / DISSECTOR}")
        if args.no_extcap:
            return 0
        extcap_dir, read_by_wireshark = (args.extcap_dir, True) if args.extcap_dir else default_extcap_dir(folders)
        entry = install_extcap(extcap_dir)
    except OSError as exc:
        print(f"{prog}: cannot install: {exc}", file=sys.stderr)
        return 2
    print(f"extcap: {entry}")
    if not read_by_wireshark:
        print(f"note: this Wireshark reads no personal extcap folder (4.2 and later do); "
              f"start it as WIRESHARK_EXTCAP_DIR={extcap_dir} wireshark (that replaces the global "
              f"extcap folder), or copy {entry.name} into the folder `tshark -G folders` calls "
              f"\"Extcap path\"", file=sys.stderr)
    return 0


__all__ = ["DISSECTOR", "add_arguments", "dissector_path", "install_extcap", "run", "wireshark_folders"]
