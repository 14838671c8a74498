"""``epos-link read | write | scan | nmt``: object access through an EPOS4 (and its gateway).

::

    epos-link read  URL NODE INDEX SUBINDEX [--type T] [--json]
    epos-link write URL NODE INDEX SUBINDEX VALUE [--type T]
    epos-link scan  URL [--nodes 1-127] [--node-timeout S] [--json]
    epos-link nmt   URL NODE start|stop|preop|reset|reset-comm

Types: ``u8 u16 u32 i8 i16 i32`` (default ``u32``) use ReadObject/WriteObject
(guide 2.1.1.1, 2.1.2.1); ``str`` and ``bytes`` read the whole object by
segmented read, and write by WriteObject up to 4 bytes, else by segmented write
(node 0 or --gateway-id only, guide 2.1.2.2). NODE 0 is the connected EPOS4;
other ids are forwarded by its CAN gateway (guide chapter 5). Numbers are
decimal or 0x-hex.

One module serves four subcommands: ``epos_link.cli`` builds each
subparser with ``add_arguments`` and the subcommand is told apart by the
subparser's name (the last word of its ``prog``).
"""
from __future__ import annotations

import argparse
import json
import sys
from typing import Callable

from ..capture import CaptureFormatError, parse_hex
from ..client import NMT_COMMANDS, EposClient
from ..errors import LocalProtocolError
from .common import add_link_options, add_url, guarded, open_client, parse_int, positive_float

# name -> (size in bytes, signed)
INT_TYPES: dict[str, tuple[int, bool]] = {
    "u8": (1, False), "u16": (2, False), "u32": (4, False),
    "i8": (1, True), "i16": (2, True), "i32": (4, True),
}
TYPES = [*INT_TYPES, "str", "bytes"]


def _hex(data: bytes) -> str:
    return data.hex(" ").upper() or "(empty)"


def _address_arguments(parser: argparse.ArgumentParser) -> None:
    add_url(parser)
    parser.add_argument("node", metavar="NODE", type=parse_int,
                        help="CANopen node id: 0 = the connected EPOS4, 1..127 = via its gateway")
    parser.add_argument("index", metavar="INDEX", type=parse_int, help="object index (0x6064 or 24676)")
    parser.add_argument("subindex", metavar="SUBINDEX", type=parse_int, help="object subindex")


def _add_read(parser: argparse.ArgumentParser) -> None:
    _address_arguments(parser)
    parser.add_argument("--type", choices=TYPES, default="u32", help="value type (default u32)")
    parser.add_argument("--json", action="store_true",
                        help='print {"node", "index", "subindex", "data": hex of the bytes read}')
    add_link_options(parser)


def _add_write(parser: argparse.ArgumentParser) -> None:
    _address_arguments(parser)
    parser.add_argument("value", metavar="VALUE",
                        help="a number for integer types, text for str, hex bytes for bytes")
    parser.add_argument("--type", choices=TYPES, default="u32", help="value type (default u32)")
    add_link_options(parser)


def _node_list(text: str) -> list[int]:
    """``1-127``, ``1,2,5`` or a mix (``1-4,10``)."""
    nodes: list[int] = []
    try:
        for part in text.split(","):
            lo, _, hi = part.partition("-")
            first = parse_int(lo)
            nodes.extend(range(first, parse_int(hi) + 1) if hi else [first])
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a node list like 1-127 or 1,2,5") from None
    return nodes


def _add_scan(parser: argparse.ArgumentParser) -> None:
    add_url(parser)
    parser.add_argument("--nodes", type=_node_list, default=list(range(1, 128)), metavar="LIST",
                        help="node ids to try: 1-127 (default), 1,2,5, 0-3,10")
    parser.add_argument("--node-timeout", type=positive_float, default=0.1, metavar="SECONDS",
                        help="how long to wait for each node's device type (default 0.1)")
    parser.add_argument("--json", action="store_true", help="one JSON object per node found")
    add_link_options(parser)


def _add_nmt(parser: argparse.ArgumentParser) -> None:
    add_url(parser)
    parser.add_argument("node", metavar="NODE", type=parse_int, help="node id, 0 = all nodes")
    parser.add_argument("command", choices=list(NMT_COMMANDS), help="NMT command (guide Table 3-14)")
    add_link_options(parser)


def decode_value(data: bytes, type_name: str) -> str:
    """The typed value of bytes read, for display."""
    if type_name in INT_TYPES:
        size, signed = INT_TYPES[type_name]
        value = int.from_bytes(data[:size], "little", signed=signed)
        return f"{type_name} {value} (0x{value & ((1 << 8 * size) - 1):0{2 * size}X})"
    if type_name == "str":
        return "str " + json.dumps(data.rstrip(b"\x00").decode("utf-8", errors="replace"))
    return f"bytes {len(data)}"


def encode_value(text: str, type_name: str) -> bytes:
    """The bytes to write for VALUE given as text."""
    if type_name in INT_TYPES:
        size, signed = INT_TYPES[type_name]
        try:
            value = parse_int(text)
        except argparse.ArgumentTypeError as exc:
            raise LocalProtocolError(str(exc)) from None
        lo, hi = (-(1 << (8 * size - 1)), (1 << (8 * size - 1)) - 1) if signed else (0, (1 << 8 * size) - 1)
        if not lo <= value <= hi:
            raise LocalProtocolError(f"{text} is out of range for {type_name} ({lo}..{hi})")
        return value.to_bytes(size, "little", signed=signed)
    if type_name == "str":
        return text.encode("utf-8")
    try:
        return parse_hex(text)
    except CaptureFormatError as exc:
        raise LocalProtocolError(str(exc)) from None


def _read(args: argparse.Namespace, client: EposClient) -> int:
    if args.type in INT_TYPES:
        data = client.read_object(args.node, args.index, args.subindex)
    else:
        data = client.upload(args.node, args.index, args.subindex)
    if args.json:
        print(json.dumps({"node": args.node, "index": args.index, "subindex": args.subindex,
                          "data": data.hex()}))
    else:
        print(f"{_hex(data)} -> {decode_value(data, args.type)}")
    return 0


def _write(args: argparse.Namespace, client: EposClient) -> int:
    data = encode_value(args.value, args.type)
    client.download(args.node, args.index, args.subindex, data)
    print(f"wrote {_hex(data)} to node {args.node} 0x{args.index:04X}/0x{args.subindex:02X}")
    return 0


def _scan(args: argparse.Namespace, client: EposClient) -> int:
    found = client.scan(args.nodes, timeout=args.node_timeout)
    for info in found:
        if args.json:
            print(json.dumps(info.as_dict()))
            continue
        ids = " ".join(f"{k}=0x{v:08X}" for k, v in (
            ("vendor", info.vendor_id), ("product", info.product_code),
            ("revision", info.revision), ("serial", info.serial_number)) if v is not None)
        name = json.dumps(info.name) if info.name is not None else "-"
        print(f"node {info.node:3d}  type=0x{info.device_type:08X}  name={name}  {ids}".rstrip())
    if not found:
        print(f"epos-link scan: no node answered on {args.url}", file=sys.stderr)
        return 2
    return 0


def _nmt(args: argparse.Namespace, client: EposClient) -> int:
    client.nmt(args.node, args.command)
    print(f"sent NMT {args.command} to {'all nodes' if args.node == 0 else f'node {args.node}'}")
    return 0


COMMANDS: dict[str, tuple[Callable[[argparse.ArgumentParser], None],
                          Callable[[argparse.Namespace, EposClient], int]]] = {
    "read": (_add_read, _read),
    "write": (_add_write, _write),
    "scan": (_add_scan, _scan),
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
            return COMMANDS[name][1](args, client)

    return guarded(prog, body)


__all__ = ["COMMANDS", "INT_TYPES", "TYPES", "add_arguments", "decode_value", "encode_value", "run"]
