"""``epos-link backup`` and ``restore``: a node's parameters to a DCF and back.

::

    epos-link backup  URL NODE [--eds FILE] -o FILE.dcf   (-o -: standard output)
    epos-link restore URL NODE FILE.dcf [--dry-run] [--force] [--changes-only]

Backup reads every readable object of the object dictionary (the shipped
EPOS4 EDS, or ``--eds``) and writes a DCF (CiA 306 with ``ParameterValue``)
through canopen's ``export_od``, so ``canopen.import_od`` loads it back.
Restore loads the DCF with ``canopen.import_od`` and, object by object in
index order, reports one outcome:

* ``written``    the device held another value and took the DCF's;
* ``unchanged``  the device already holds the DCF's value (nothing sent);
* ``skipped``    read-only or constant in the DCF, or a command object (below);
* ``refused``    the device answered an abort code (printed with its name), or
  the link failed for that object. One failure never stops the rest; objects
  refused for a value range or parameter conflict (an order dependency, e.g.
  a limit written before the value it limits) are tried once more at the end.

Command objects are never written back, because writing them does something
(CiA 301 1010h/1011h store and restore; CiA 402 6040h controlword, 6060h modes
of operation and the targets 607Ah, 60FFh, 6071h): a restore must not enable,
switch or move a drive. A restore to a drive whose statusword (6041h) says
"operation enabled" is refused unless ``--force``. ``--dry-run`` reads and
compares but writes nothing. ``--changes-only`` leaves the ``unchanged`` and
``skipped`` lines out. A summary line ends every run, an interrupted one
(Ctrl-C, exit 130) included: a backup then says how far it got and writes no DCF
(a DCF with part of the objects would restore part of a drive's parameters, and
an older file of that name is left as it was).

Exit codes: 0 all done, 1 something was refused (or unreadable in a backup),
130 interrupted (after its summary),
2 usage errors and failures before the first object.
"""
from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from typing import IO, Any, Optional

import canopen
from canopen.objectdictionary import ODVariable

from ..client import EposClient
from ..errors import DeviceError, EposError
from .access import _node
from .common import add_link_options, add_url, guarded, open_client
from .objects import ObjectDirectory, ObjectInfo, ObjectLookupError, ValueType, default_eds
from .scan import Progress

COMMAND_OBJECTS: dict[int, str] = {
    0x1010: "store parameters, a command (CiA 301 7.5.2.13)",
    0x1011: "restore default parameters, a command (CiA 301 7.5.2.14)",
    0x6040: "controlword, a command that can enable the drive (CiA 402)",
    0x6060: "modes of operation, changes what an enabled drive does (CiA 402)",
    0x607A: "target position, starts a move (CiA 402)",
    0x60FF: "target velocity, starts a move (CiA 402)",
    0x6071: "target torque (CiA 402)",
}
STATUSWORD = 0x6041
# CiA 402 statusword xxxx xxxx x01x 0111 = operation enabled.
_ENABLED_MASK, _ENABLED = 0x006F, 0x0027
# Refusals that an order dependency can cause: tried again after the others.
_RETRY_CODES = frozenset({0x06090030, 0x06090031, 0x06090032, 0x06040043, 0x08000022})


@dataclass
class Outcome:
    info: ObjectInfo
    result: str          # written, unchanged, skipped, refused, read, unreadable
    detail: str = ""
    code: Optional[int] = None


def _add_common(parser: argparse.ArgumentParser) -> None:
    add_url(parser)
    parser.add_argument("node", metavar="NODE", type=_node,
                        help="node id: 0 = the connected EPOS4, 1..127 = via its gateway")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    name = parser.prog.rsplit(" ", 1)[-1]
    _add_common(parser)
    if name == "backup":
        parser.add_argument("--eds", metavar="FILE", help="object dictionary to read (default: the shipped EPOS4 EDS)")
        parser.add_argument("-o", "--output", required=True, metavar="FILE.dcf",
                            help="the DCF to write; - for standard output")
    else:
        parser.add_argument("dcf", metavar="FILE.dcf", help="a DCF written by epos-link backup (or any DCF)")
        parser.add_argument("--dry-run", action="store_true", help="compare and report, write nothing")
        parser.add_argument("--force", action="store_true", help="restore even to a drive in operation enabled")
        parser.add_argument("--changes-only", action="store_true",
                            help="print only objects written, refused or (dry run) differing; "
                                 "the summary still counts all")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar on a terminal")
    add_link_options(parser)
    parser.set_defaults(_backup=name)


def _load_od(path: str, node_id: int) -> canopen.ObjectDictionary:
    """A fresh dictionary (values get set on it), parsed by canopen."""
    try:
        return canopen.import_od(path, node_id)
    except FileNotFoundError:
        raise ObjectLookupError(f"{path}: no such file") from None
    except Exception as exc:  # canopen raises many kinds on a bad file
        raise ObjectLookupError(f"{path}: cannot parse it ({type(exc).__name__}: {exc})") from None


def read_bytes(client: EposClient, node: int, info: ObjectInfo) -> bytes:
    typ = info.type
    if typ is not None and typ.small:
        return client.read_object(node, info.index, info.subindex)[:typ.size]
    return client.upload(node, info.index, info.subindex)


def _bar(done: int, total: int, text: str, width: int = 24) -> str:
    filled = width * done // max(total, 1)
    return f"[{'#' * filled}{'.' * (width - filled)}] {done}/{total} {text}"[:100]


def _failure(exc: EposError) -> tuple[str, Optional[int]]:
    if isinstance(exc, DeviceError):
        return f"0x{exc.code:08X} {exc.name}", exc.code
    return f"{type(exc).__name__}: {exc}", None


def backup(client: EposClient, node: int, od: canopen.ObjectDictionary, progress: Progress,
           outcomes: Optional[list[Outcome]] = None) -> list[Outcome]:
    """Read every readable object into ``od`` (``var.value``); one outcome per object,
    appended to ``outcomes`` as it comes (pass a list to keep them when interrupted)."""
    directory = ObjectDirectory(od)
    entries = directory.variables()
    outcomes = [] if outcomes is None else outcomes
    for i, info in enumerate(entries, 1):
        progress.show(_bar(i, len(entries), f"0x{info.index:04X}/0x{info.subindex:02X} {info.name}"))
        if not info.readable:
            outcomes.append(Outcome(info, "skipped", "write-only"))
            continue
        if info.type is None:
            outcomes.append(Outcome(info, "skipped", "type unknown to epos-link"))
            continue
        try:
            value = info.type.decode(read_bytes(client, node, info))
        except EposError as exc:
            detail, code = _failure(exc)
            outcomes.append(Outcome(info, "unreadable", detail, code))
            continue
        var = directory.variable(info.index, info.subindex)
        assert var is not None
        var.value = value  # type: ignore[assignment]  # canopen types it narrower than it takes
        var.value_raw = None  # type: ignore[attr-defined]  # canopen's DCF writer reads it
        outcomes.append(Outcome(info, "read", info.type.format(value)))
    progress.clear()
    return outcomes


def _dcf_value(var: ODVariable, typ: ValueType) -> Any:
    value = var.value
    if typ.kind == "bytes" and isinstance(value, str):
        return bytes.fromhex(value)
    return value


QUIET_RESULTS = frozenset({"unchanged", "skipped"})  # left out by --changes-only


def restore(client: EposClient, node: int, od: canopen.ObjectDictionary, *, dry_run: bool,
            progress: Progress, out: IO[str], changes_only: bool = False,
            outcomes: Optional[list[Outcome]] = None) -> list[Outcome]:
    """Restore ``od``'s values; one outcome per object, appended to ``outcomes`` as it
    comes (pass a list to keep them when interrupted)."""
    directory = ObjectDirectory(od)
    todo = [info for info in directory.variables()
            if getattr(directory.variable(info.index, info.subindex), "value", None) is not None]
    outcomes = [] if outcomes is None else outcomes
    retry: list[ObjectInfo] = []

    def report(outcome: Outcome) -> None:
        progress.clear()
        if changes_only and outcome.result in QUIET_RESULTS:
            return
        info = outcome.info
        out.write(f"{outcome.result:<9} 0x{info.index:04X}/0x{info.subindex:02X} {info.name}"
                  + (f": {outcome.detail}" if outcome.detail else "") + "\n")
        out.flush()

    def one(info: ObjectInfo, last_try: bool) -> None:
        var = directory.variable(info.index, info.subindex)
        assert var is not None and info.type is not None
        typ = info.type
        want = typ.encode(_dcf_value(var, typ))
        current: Optional[bytes] = None
        try:
            current = read_bytes(client, node, info)
        except EposError:
            pass  # unreadable now: write it anyway
        if current is not None and typ.decode(current) == typ.decode(want):
            outcomes.append(Outcome(info, "unchanged", typ.format(typ.decode(want))))
            report(outcomes[-1])
            return
        change = (f"{typ.format(typ.decode(current))} -> " if current is not None else "") + typ.format(typ.decode(want))
        if dry_run:
            outcomes.append(Outcome(info, "differs", change + " (dry run: not written)"))
            report(outcomes[-1])
            return
        try:
            client.download(node, info.index, info.subindex, want)
        except EposError as exc:
            detail, code = _failure(exc)
            if not last_try and code in _RETRY_CODES:
                retry.append(info)
                return
            outcomes.append(Outcome(info, "refused", detail, code))
        else:
            outcomes.append(Outcome(info, "written", change))
        report(outcomes[-1])

    for i, info in enumerate(todo, 1):
        progress.show(_bar(i, len(todo), f"0x{info.index:04X}/0x{info.subindex:02X} {info.name}"))
        if not info.writable:
            outcomes.append(Outcome(info, "skipped", f"{info.access or 'read-only'} (read-only)"))
            report(outcomes[-1])
        elif info.index in COMMAND_OBJECTS:
            outcomes.append(Outcome(info, "skipped", COMMAND_OBJECTS[info.index]))
            report(outcomes[-1])
        elif info.type is None:
            outcomes.append(Outcome(info, "skipped", "type unknown to epos-link"))
            report(outcomes[-1])
        else:
            one(info, last_try=False)
    for info in retry:  # order dependencies: once more, after all the others
        one(info, last_try=True)
    progress.clear()
    return outcomes


def _enabled(client: EposClient, node: int, od: canopen.ObjectDictionary) -> Optional[int]:
    """The statusword when it says operation enabled, else None."""
    if STATUSWORD not in od:
        return None
    try:
        sw = int.from_bytes(client.read_object(node, STATUSWORD, 0)[:2], "little")
    except EposError:
        return None
    return sw if sw & _ENABLED_MASK == _ENABLED else None


def _summary(outcomes: list[Outcome]) -> str:
    counts: dict[str, int] = {}
    for o in outcomes:
        counts[o.result] = counts.get(o.result, 0) + 1
    return ", ".join(f"{n} {k}" for k, n in counts.items()) or "nothing to do"


def run(args: argparse.Namespace) -> int:
    name: str = args._backup
    prog = f"epos-link {name}"

    def body() -> int:
        progress = Progress(sys.stderr, not args.no_progress and sys.stderr.isatty())
        node_id = max(args.node, 1)
        if name == "backup":
            od = _load_od(str(args.eds or default_eds()), node_id)
            outcomes: list[Outcome] = []
            try:
                with open_client(args) as client:
                    backup(client, args.node, od, progress, outcomes)
            except KeyboardInterrupt:
                progress.clear()
                total = len(ObjectDirectory(od).variables())
                where = "standard output" if args.output == "-" else args.output
                done = _summary(outcomes) if outcomes else "nothing read"
                print(f"{prog}: interrupted after {len(outcomes)} of {total} objects: {done}; "
                      f"{where} not written", file=sys.stderr)
                return 130
            od.node_id = node_id
            od.comments = (f"Backup of node {args.node} at {args.url} by epos-link, "
                           f"{time.strftime('%Y-%m-%d %H:%M:%S')}")
            # "-o -": the DCF is standard output, so everything else goes to standard error.
            to_stdout = args.output == "-"
            notes = sys.stderr if to_stdout else sys.stdout
            for o in outcomes:
                if o.result == "unreadable":
                    print(f"unreadable 0x{o.info.index:04X}/0x{o.info.subindex:02X} {o.info.name}: {o.detail}",
                          file=notes)
            try:
                canopen.export_od(od, sys.stdout if to_stdout else args.output, doc_type="dcf")
                sys.stdout.flush()
            except OSError as exc:
                print(f"{prog}: cannot write {args.output}: {exc}", file=sys.stderr)
                return 2
            where = "standard output" if to_stdout else args.output
            print(f"{prog}: {_summary(outcomes)}; wrote {where}", file=sys.stderr)
            return 1 if any(o.result == "unreadable" for o in outcomes) else 0
        od = _load_od(args.dcf, node_id)
        with open_client(args) as client:
            sw = _enabled(client, args.node, od)
            if sw is not None and not args.force and not args.dry_run:
                print(f"{prog}: node {args.node} is in operation enabled (statusword 0x{sw:04X}): "
                      "disable it first, or pass --force", file=sys.stderr)
                return 2
            outcomes = []
            try:
                restore(client, args.node, od, dry_run=args.dry_run, progress=progress, out=sys.stdout,
                        changes_only=args.changes_only, outcomes=outcomes)
            except KeyboardInterrupt:
                # A summary on every exit: what was done before Ctrl-C is what the drive holds.
                progress.clear()
                print(f"{prog}: interrupted: {_summary(outcomes)}"
                      + (" (dry run)" if args.dry_run else ""), file=sys.stderr)
                return 130
        print(f"{prog}: {_summary(outcomes)}" + (" (dry run)" if args.dry_run else ""), file=sys.stderr)
        return 1 if any(o.result == "refused" for o in outcomes) else 0

    return guarded(prog, body)


__all__ = ["COMMAND_OBJECTS", "Outcome", "add_arguments", "backup", "restore", "run"]
