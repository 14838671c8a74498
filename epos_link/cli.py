"""The ``epos-link`` command line: a thin dispatcher over the tools.

Each subcommand lives in its own module with ``add_arguments(parser)`` and
``run(args) -> int``; modules are imported only when their command runs, so a
missing optional dependency breaks only the command that needs it.
Exit codes: 0 success, 1 the device or the data reported an error,
2 usage errors, timeouts and unreachable ports.
"""
from __future__ import annotations

import argparse
import importlib
import sys
from typing import Optional, Sequence

# name -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "decode": ("epos_link.tools.decode", "decode frames from hex or a capture file"),
    "read": ("epos_link.tools.access", "read an object of a node (ReadObject or segmented read)"),
    "write": ("epos_link.tools.access", "write an object of a node (WriteObject or segmented write)"),
    "scan": ("epos_link.tools.access", "find the CANopen nodes that answer (0x1000, 0x1008, 0x1018)"),
    "nmt": ("epos_link.tools.access", "send an NMT command (SendNMTService)"),
    "ports": ("epos_link.tools.ports", "list serial ports and EPOS4 USB devices"),
    "sim": ("epos_link.tools.sim", "serve a simulated EPOS4 on a pty or TCP"),
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="epos-link", description="maxon EPOS4 USB/RS232 protocol tools")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name, (module, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.set_defaults(_module=module)
        importlib.import_module(module).add_arguments(p)
    return parser


def main(argv: Optional[Sequence[str]] = None) -> int:
    from importlib.metadata import version  # the installed distribution, as pip shows it

    parser = build_parser()
    parser.add_argument("--version", action="version", version=f"%(prog)s {version('epos-link')}")
    args = parser.parse_args(argv)
    module = importlib.import_module(args._module)
    try:
        return int(module.run(args))
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:  # output piped into `head`
        return 0


if __name__ == "__main__":
    sys.exit(main())
