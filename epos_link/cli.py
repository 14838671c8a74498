"""The ``epos-link`` command line: a thin dispatcher over the tools.

Each subcommand lives in its own module with ``add_arguments(parser)`` and
``run(args) -> int``; modules are imported only when their command runs, so a
missing optional dependency breaks only the command that needs it.
Exit codes: 0 success, 1 the device or the data reported an error,
2 usage errors (one line, :mod:`epos_link.cli_parser`), timeouts, a silent EPOS4 and unreachable ports.
"""
from __future__ import annotations

import argparse
import importlib
import sys
from typing import Optional, Sequence

from .cli_parser import OneLineParser

# name -> (module, one-line help, one example)
COMMANDS: dict[str, tuple[str, str, str]] = {
    "read": ("epos_link.tools.access", "read an object by index or name, typed by the EDS",
             'epos-link read /dev/ttyUSB0 1 "Position actual value"'),
    "write": ("epos_link.tools.access", "write an object by index or name, typed by the EDS",
              "epos-link write /dev/ttyUSB0 1 0x6081 0 1000"),
    "scan": ("epos_link.tools.scan", "find the CANopen nodes that answer, printing each as found",
             "epos-link scan /dev/ttyUSB0 --nodes 1-10"),
    "nmt": ("epos_link.tools.access", "send an NMT command (SendNMTService)",
            "epos-link nmt /dev/ttyUSB0 0 start"),
    "monitor": ("epos_link.tools.monitor", "a transparent proxy that shows every frame between an "
                "application and the device", "epos-link monitor /dev/ttyUSB0 --pty --record cap.txt"),
    "decode": ("epos_link.tools.decode", "decode frames from hex, a capture file or standard input",
               "epos-link decode --follow cap.txt"),
    "export": ("epos_link.tools.export", "write a capture as pcapng for Wireshark",
               "epos-link export cap.txt -o cap.pcapng"),
    "wireshark": ("epos_link.tools.wireshark", "the Wireshark dissector: print its path or install it",
                  "tshark -X lua_script:$(epos-link wireshark path) -r cap.pcapng"),
    "backup": ("epos_link.tools.backup", "read every readable object of a node into a DCF",
               "epos-link backup /dev/ttyUSB0 1 -o drive1.dcf"),
    "restore": ("epos_link.tools.backup", "write back the objects of a DCF that differ",
                "epos-link restore /dev/ttyUSB0 1 drive1.dcf --dry-run"),
    "ports": ("epos_link.tools.ports", "list serial ports and EPOS4 USB devices", "epos-link ports"),
    "record": ("epos_link.tools.record", "sample objects of one node over time into CSV and a plot",
               "epos-link record /dev/ttyUSB0 --node 1 position_actual_value statusword --plot move.png"),
    "watch": ("epos_link.tools.watch", "a live table of objects (statusword decoded), q quits",
              "epos-link watch /dev/ttyUSB0 --node 2 Statusword 0x6064"),
    "sim": ("epos_link.tools.sim", "serve a simulated EPOS4 on a pty or TCP",
            "epos-link sim --tcp 127.0.0.1:0 --drives 2,3"),
}


def _overview() -> str:
    width = max(map(len, COMMANDS))
    lines = ["commands:"]
    for name, (_, help_text, example) in COMMANDS.items():
        lines.append(f"  {name:<{width}}  {help_text}")
        lines.append(f"  {'':<{width}}    e.g. {example}")
    lines.append("")
    lines.append("URLs: a serial device (/dev/ttyUSB0, COM3), usb://, socket://HOST:PORT, sim://, "
                 "replay://CAPTURE.txt")
    lines.append("'epos-link COMMAND --help' tells more.")
    return "\n".join(lines)


def chosen_command(argv: Sequence[str]) -> Optional[str]:
    """The subcommand ``argv`` names: its first word that is not an option (the top-level
    parser takes no option with a value), if it is a command."""
    first = next((a for a in argv if not a.startswith("-")), None)
    return first if first in COMMANDS else None


def build_parser(argv: Optional[Sequence[str]] = None) -> argparse.ArgumentParser:
    """The parser; only the module of the command ``argv`` names is imported for its
    arguments (``None``: every command's), so ``epos-link --version`` or ``epos-link read``
    does not pay for matplotlib, canopen or pyusb, which other commands import
    (issue 32: a spawned ``epos-link`` starts fast)."""
    wanted = set(COMMANDS) if argv is None else {chosen_command(argv)}
    parser = OneLineParser(
        prog="epos-link", description="maxon EPOS4 USB/RS232 protocol tools",
        epilog=_overview(), formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name, (module, help_text, example) in COMMANDS.items():
        p = sub.add_parser(name, description=f"{help_text}. Example: {example}")
        p.set_defaults(_module=module)
        if name in wanted:
            importlib.import_module(module).add_arguments(p)
    return parser


class _Version(argparse.Action):
    """``--version``: the installed distribution's version, as pip shows it, looked up
    only when asked (importlib.metadata costs a spawned command ~0.1 s)."""

    def __init__(self, option_strings: Sequence[str], dest: str = argparse.SUPPRESS,
                 default: str = argparse.SUPPRESS, help: str = "show program's version number and exit"
                 ) -> None:
        super().__init__(option_strings, dest=dest, default=default, nargs=0, help=help)

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace,
                 values: object, option_string: Optional[str] = None) -> None:
        from importlib.metadata import version

        print(f"{parser.prog} {version('epos-link')}")  # stdout, as argparse's own action
        parser.exit()


def main(argv: Optional[Sequence[str]] = None) -> int:
    if argv is None:
        argv = sys.argv[1:]
    parser = build_parser(argv)
    parser.add_argument("--version", action=_Version)
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
