"""``epos-link read | write | nmt``: object access through an EPOS4 (and its gateway).

::

    epos-link read  URL NODE (INDEX [SUBINDEX] | INDEX/SUBINDEX | NAME) [--type T] [--eds FILE] [--json]
    epos-link write URL NODE (INDEX [SUBINDEX] | INDEX/SUBINDEX | NAME) VALUE [--type T] [--eds FILE]
    epos-link nmt   URL NODE start|stop|preop|reset|reset-comm

An object is named by index (0x6064 or 24676, subindex 0 when left out; the
subindex after a slash, 0x1018/4, or as the next argument) or by
its name in the object dictionary (``"Position actual value"``,
``position_actual_value``, ``"Identity object.Serial number"``; see
:mod:`epos_link.tools.objects`). The dictionary is the shipped EPOS4 EDS, or
``--eds FILE`` (an EDS or DCF). Its data type decodes and encodes the value;
``--type`` overrides it. An object the dictionary does not know is read as
``u32`` with a warning on standard error.

Objects of up to 4 bytes travel by ReadObject/WriteObject (guide 2.1.1.1,
2.1.2.1); longer ones (strings, domains, 64-bit numbers) by segmented read,
and by segmented write to node 0 or --gateway-id only (guide 2.1.2.2). NODE 0
is the connected EPOS4; other ids are forwarded by its CAN gateway (guide
chapter 5). Numbers are decimal or 0x-hex.

One module serves three subcommands: ``epos_link.cli`` builds each
subparser with ``add_arguments`` and the subcommand is told apart by the
subparser's name (the last word of its ``prog``).
"""
from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from typing import Callable, Optional

from ..client import NMT_COMMANDS, EposClient
from ..errors import EposTimeoutError, LocalProtocolError
from .common import (add_link_options, add_url, guarded, open_client, parse_int,
                     device_silent, require_device)
from .objects import TYPE_NAMES, TYPES, ObjectInfo, ValueType, load_directory, meaning

DEFAULT_TYPE = "u32"


def _hex(data: bytes) -> str:
    return data.hex(" ").upper() or "(empty)"


def _node(text: str) -> int:
    node = parse_int(text)
    if not 0 <= node <= 127:
        raise argparse.ArgumentTypeError(f"node ids are 0..127, got {node}")
    return node


def _object_arguments(parser: argparse.ArgumentParser) -> None:
    add_url(parser)
    parser.add_argument("node", metavar="NODE", type=_node,
                        help="CANopen node id: 0 = the connected EPOS4, 1..127 = via its gateway")
    parser.add_argument("object", metavar="INDEX|NAME",
                        help='object index (0x6064 or 24676, or with its subindex 0x1018/4) '
                        'or name ("Position actual value")')


def _dictionary_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--type", choices=TYPE_NAMES, default=None,
                        help="value type, overriding the object dictionary's")
    parser.add_argument("--eds", metavar="FILE",
                        help="object dictionary (EDS or DCF) for names and types (default: the shipped EPOS4 EDS)")


def _add_read(parser: argparse.ArgumentParser) -> None:
    _object_arguments(parser)
    parser.add_argument("subindex", metavar="SUBINDEX", nargs="?", type=parse_int, default=None,
                        help="object subindex (default 0)")
    _dictionary_options(parser)
    parser.add_argument("--json", action="store_true",
                        help='print {"node", "index": "0x6041", "subindex": "0x00", "name", "type", "value", '
                        '"meaning" (statusword: its CiA 402 state), "raw" (the value\'s bytes), '
                        '"data" (every byte the device answered, padding included)}')
    add_link_options(parser)


def _add_write(parser: argparse.ArgumentParser) -> None:
    _object_arguments(parser)
    parser.add_argument("rest", metavar="[SUBINDEX] VALUE", nargs="+",
                        help="a number for integer types, text for strings, hex for bytes")
    _dictionary_options(parser)
    add_link_options(parser)


def _add_nmt(parser: argparse.ArgumentParser) -> None:
    add_url(parser)
    parser.add_argument("node", metavar="NODE", type=parse_int, help="node id, 0 = all nodes")
    parser.add_argument("command", choices=list(NMT_COMMANDS), help="NMT command (guide Table 3-14)")
    add_link_options(parser)


@dataclass(frozen=True)
class Target:
    """The object a command addresses, and the type its value is read with."""

    node: int
    index: int
    subindex: int
    info: Optional[ObjectInfo]
    type: ValueType

    @property
    def name(self) -> Optional[str]:
        return self.info.name if self.info else None

    def describe(self) -> str:
        where = f"node {self.node} 0x{self.index:04X}/0x{self.subindex:02X}"
        return f"{where} {self.name}" if self.name else where


def resolve_target(args: argparse.Namespace, subindex_text: Optional[str]) -> Target:
    """INDEX [SUBINDEX], INDEX/SUBINDEX or NAME [SUBINDEX] against the dictionary
    (:meth:`ObjectDirectory.locate`, the parser ``watch`` and ``record`` use too);
    warns (stderr) when the type is a guess."""
    directory = load_directory(args.eds, max(args.node, 1))
    try:
        subindex = parse_int(subindex_text) if subindex_text is not None else None
    except argparse.ArgumentTypeError as exc:
        raise LocalProtocolError(f"SUBINDEX: {exc}") from None
    index, sub, info = directory.locate(args.object, subindex)
    if args.type:
        typ = TYPES[args.type]
    elif info is not None and info.type is not None:
        typ = info.type
    else:
        typ = TYPES[DEFAULT_TYPE]
        what = "has no type we know" if info else "is not in the object dictionary"
        print(f"epos-link: warning: 0x{index:04X}/0x{sub:02X} {what} ({directory.source}): "
              f"taken as {DEFAULT_TYPE}; --type picks another", file=sys.stderr)
    return Target(args.node, index, sub, info, typ)


def read_value(client: EposClient, target: Target) -> bytes:
    """The object's bytes: ReadObject for types of up to 4 bytes, else a segmented read."""
    if target.type.small:
        return client.read_object(target.node, target.index, target.subindex)
    return client.upload(target.node, target.index, target.subindex)


def _read(args: argparse.Namespace, client: EposClient) -> int:
    target = resolve_target(args, None if args.subindex is None else str(args.subindex))
    data = read_value(client, target)
    typ = target.type
    value = typ.decode(data)
    shown = data[:typ.size] if typ.size is not None else data
    note = meaning(target.index, target.subindex, value)
    if args.json:
        # Indexes as hex strings, as every other output shows them (0x6041, not 24641).
        out = {"node": target.node, "index": f"0x{target.index:04X}",
               "subindex": f"0x{target.subindex:02X}", "name": target.name, "type": typ.name,
               "value": value.hex() if isinstance(value, bytes) else value,
               "raw": shown.hex(), "data": data.hex()}
        if note is not None:
            out["meaning"] = note
        print(json.dumps(out))
    else:
        name = f"  {target.name}" if target.name else ""
        shown_note = f" [{note}]" if note is not None else ""
        print(f"{_hex(shown)} -> {typ.name} {typ.format(value)}{shown_note}{name}")
    return 0


def _write(args: argparse.Namespace, client: EposClient) -> int:
    if len(args.rest) > 2:
        raise LocalProtocolError(f"expected [SUBINDEX] VALUE, got {len(args.rest)} words: "
                                 f"quote a value with spaces")
    subindex_text = args.rest[0] if len(args.rest) == 2 else None
    target = resolve_target(args, subindex_text)
    typ = target.type
    data = typ.encode(typ.parse(args.rest[-1]))
    client.download(target.node, target.index, target.subindex, data)
    print(f"wrote {typ.name} {typ.format(typ.decode(data))} [{_hex(data)}] to {target.describe()}")
    return 0


def _nmt(args: argparse.Namespace, client: EposClient) -> int:
    client.nmt(args.node, args.command)
    print(f"sent NMT {args.command} to {'all nodes' if args.node == 0 else f'node {args.node}'}")
    return 0


COMMANDS: dict[str, tuple[Callable[[argparse.ArgumentParser], None],
                          Callable[[argparse.Namespace, EposClient], int]]] = {
    "read": (_add_read, _read),
    "write": (_add_write, _write),
    "nmt": (_add_nmt, _nmt),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    name = parser.prog.rsplit(" ", 1)[-1]
    if name not in COMMANDS:
        raise ValueError(f"epos_link.tools.access serves {', '.join(COMMANDS)}, not {name!r}")
    COMMANDS[name][0](parser)
    parser.set_defaults(_access=name)


def run(args: argparse.Namespace) -> int:
    name: str = args._access
    prog = f"epos-link {name}"

    def body() -> int:
        with open_client(args) as client:
            try:
                return COMMANDS[name][1](args, client)
            except EposTimeoutError as exc:
                # A node behind a working gateway is answered for (0x05040000): no
                # answer at all may be a silent EPOS4. Node 0 is the EPOS4 itself;
                # for another node, ask it, and say so if it is silent.
                if args.node == 0:
                    raise device_silent(args.url, args.baud, exc) from exc
                require_device(client, args.url, args.baud)
                raise

    return guarded(prog, body)


__all__ = ["COMMANDS", "Target", "add_arguments", "read_value", "resolve_target", "run"]
