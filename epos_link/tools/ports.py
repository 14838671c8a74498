"""``epos-link ports``: the serial ports and EPOS4 USB devices of this computer.

Each line starts with the URL to pass to the other commands. EPOS4 units show
either as USB 24E7:3B01 (native, ``usb://?serial=...``) or as an FTDI serial
port 0403:A8B0 (``/dev/ttyUSBn``, ``COMn``).
"""
from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from ..errors import TransportError
from ..transports.usb import EPOS4_FTDI_ID, UDEV_RULE, UDEV_RULES_FILE, list_usb_devices

EPILOG = f"""\
Linux permissions: a native EPOS4 needs a udev rule for non-root users, e.g.
  echo '{UDEV_RULE}' | sudo tee {UDEV_RULES_FILE}
  sudo udevadm control --reload-rules && sudo udevadm trigger   (then replug)
Serial ports need membership of their group (usually: sudo usermod -aG dialout $USER).
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = EPILOG
    parser.add_argument("--json", action="store_true", help="one JSON object per port or device")
    parser.add_argument("--epos-only", action="store_true", help="only EPOS4 ports and devices")


def _serial_ports() -> list[dict[str, Any]]:
    from serial.tools import list_ports

    rows = []
    for p in sorted(list_ports.comports(), key=lambda p: p.device):
        ids = f"{p.vid:04X}:{p.pid:04X}" if p.vid is not None and p.pid is not None else None
        epos = (p.vid, p.pid) == EPOS4_FTDI_ID
        rows.append({"url": p.device, "kind": "serial", "id": ids, "epos4": epos,
                     "description": "EPOS4 (FTDI)" if epos else (p.description or ""),
                     "serial": p.serial_number})
    return rows


def _usb_devices() -> list[dict[str, Any]]:
    return [{"url": d.url, "kind": "usb", "id": "24E7:3B01", "epos4": True,
             "description": "EPOS4 (native USB)", "serial": d.serial,
             "bus": d.bus, "address": d.address} for d in list_usb_devices()]


def run(args: argparse.Namespace) -> int:
    rows = _serial_ports()
    try:
        rows += _usb_devices()
    except TransportError as exc:
        print(f"epos-link ports: USB devices not listed: {exc}", file=sys.stderr)
    if args.epos_only:
        rows = [r for r in rows if r["epos4"]]
    for row in rows:
        if args.json:
            print(json.dumps(row))
            continue
        extra = f"SN {row['serial']}" if row.get("serial") else ""
        if row["kind"] == "usb":
            extra = f"{extra} bus {row['bus']} address {row['address']}".strip()
            if not row.get("serial"):
                extra += " (serial number unreadable: permissions? see --help)"
        print(f"{row['url']:<28} {row['kind']:<6} {row['id'] or '-':<9} {row['description']}  {extra}".rstrip())
    if not rows:
        print("epos-link ports: no serial ports or EPOS4 USB devices found", file=sys.stderr)
    return 0


__all__ = ["add_arguments", "run"]
