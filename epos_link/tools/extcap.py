"""Wireshark's extcap interface to ``epos-link monitor``: live capture in Wireshark.

Wireshark runs extcap programs with these calls (Wireshark developer's guide,
"Extcap: Developer Guide"); each answer is a few lines on standard output::

    --extcap-interfaces                     extcap {version=...} / interface {value=...}{display=...}
    --extcap-interface maxon --extcap-dlts  dlt {number=147}{name=USER0}{display=...}
    --extcap-interface maxon --extcap-config   arg {number=0}{call=--device}...
    --capture --extcap-interface maxon --fifo PATH --device URL --listen HOST:PORT

A capture runs the monitor with ``--pcapng PATH`` (Wireshark's fifo) until
Wireshark stops it (SIGTERM). The application then connects to
``socket://HOST:PORT`` (default 127.0.0.1:4001) instead of the device.
"""
from __future__ import annotations

import argparse
import contextlib
import os
import sys
from typing import Optional, Sequence

from .pcapng import LINKTYPE_USER0

INTERFACE = "maxon"
DEFAULT_LISTEN = "127.0.0.1:4001"


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="epos_link_extcap", description=__doc__.splitlines()[0])
    p.add_argument("--extcap-interfaces", action="store_true")
    p.add_argument("--extcap-interface")
    p.add_argument("--extcap-dlts", action="store_true")
    p.add_argument("--extcap-config", action="store_true")
    p.add_argument("--extcap-version")
    p.add_argument("--capture", action="store_true")
    p.add_argument("--fifo")
    p.add_argument("--extcap-capture-filter")
    p.add_argument("--device", default="/dev/ttyUSB0")
    p.add_argument("--listen", default=DEFAULT_LISTEN)
    p.add_argument("--baud", default="")
    return p


def interfaces() -> str:
    return ("extcap {version=0.1.0}{help=https://pypi.org/project/epos-link}\n"
            f"interface {{value={INTERFACE}}}{{display=maxon EPOS4 (epos-link monitor)}}\n")


def dlts() -> str:
    return f"dlt {{number={LINKTYPE_USER0}}}{{name=USER0}}{{display=MAXON SERIAL V2 frames}}\n"


def config() -> str:
    return (
        "arg {number=0}{call=--device}{display=Device URL}{type=string}{default=/dev/ttyUSB0}"
        "{tooltip=The EPOS4: /dev/ttyUSB0, COM3, usb://, socket://HOST:PORT}{required=true}\n"
        f"arg {{number=1}}{{call=--listen}}{{display=Application side (HOST:PORT)}}{{type=string}}"
        f"{{default={DEFAULT_LISTEN}}}{{tooltip=The application opens socket://HOST:PORT instead of the device}}\n"
        "arg {number=2}{call=--baud}{display=Baud rate (serial ports)}{type=string}{default=}"
        "{tooltip=Leave empty for the default of 115200}\n")


def main(argv: Optional[Sequence[str]] = None) -> int:
    args = parser().parse_args(argv)
    if args.extcap_interfaces:
        sys.stdout.write(interfaces())
        return 0
    if args.extcap_interface and args.extcap_interface != INTERFACE:
        print(f"unknown interface {args.extcap_interface!r}", file=sys.stderr)
        return 2
    if args.extcap_dlts:
        sys.stdout.write(dlts())
        return 0
    if args.extcap_config:
        sys.stdout.write(config())
        return 0
    if not args.capture or not args.fifo:
        print("nothing to do: Wireshark calls this with --extcap-interfaces or --capture --fifo PATH",
              file=sys.stderr)
        return 2
    from ..cli import main as cli_main

    monitor_args = ["monitor", args.device, "--tcp", args.listen, "--pcapng", args.fifo]
    if args.baud.strip():
        monitor_args += ["--baud", args.baud.strip()]
    # The lines of the monitor are of no use to Wireshark; errors still go to stderr.
    with open(os.devnull, "w") as devnull, contextlib.redirect_stdout(devnull):
        return cli_main(monitor_args)


if __name__ == "__main__":
    sys.exit(main())
