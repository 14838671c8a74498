"""``epos-link sim``: serve a simulated EPOS4 (with drives behind its gateway).

Prints one line saying where it listens, then serves until interrupted::

    $ epos-link sim --tcp 127.0.0.1:0 --drives 2,3
    listening on socket://127.0.0.1:40123
    $ epos-link sim --pty
    listening on /dev/pts/7
    $ epos-link sim --usb --serial 1234
    listening on usb://?serial=1234: run programs as UMOCKDEV_DIR=/tmp/umockdev.Q1W2E3 umockdev-wrapper PROGRAM

With ``--can-server HOST:PORT`` the simulator's CAN bus (the drives behind the
gateway, the EPOS4 itself) is also served over the socketcand protocol
(:mod:`epos_link.simulator.socketcand`), so other programs join it::

    $ epos-link sim --tcp 127.0.0.1:0 --drives 2 --can-server 127.0.0.1:0
    listening on socket://127.0.0.1:40123
    CAN bus served over socketcand at 127.0.0.1:29536 (channel can0)
    $ python -m can.logger -i socketcand -c can0 --bus-kwargs host=127.0.0.1 port=29536

``--ethercat IFACE [--slaves N]`` serves simulated drives as EtherCAT slaves on a
network interface instead (:mod:`epos_link.simulator.ethercat`; root or CAP_NET_RAW)::

    $ sudo epos-link sim --ethercat ecatB --slaves 2
    EtherCAT: 2 simulated EPOS4 slave(s) on ecatB

With ``--usb`` a line on standard input controls the cable: ``unplug [N]``,
``replug [N]`` (unit N, default all); SIGUSR1 unplugs and SIGUSR2 replugs every unit.
"""
from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import threading
from typing import Any, Optional

from ..errors import EposError
from .common import baud_rate, parse_float, parse_int


def _host_port(text: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise argparse.ArgumentTypeError(f"expected HOST:PORT, got {text!r}")
    return host or "127.0.0.1", int(port)


def _can_server(text: str) -> tuple[str, int]:
    from ..simulator.socketcand import parse_address

    try:
        return parse_address(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def own_id_conflict(node_id: int, drives: list[int]) -> Optional[str]:
    """Why ``drives`` cannot sit behind an EPOS4 with ``node_id``, or None.

    The gateway executes requests for its own id itself (guide chapter 5), so a
    drive with that id could never be reached: refused rather than dropped.
    """
    if node_id in drives:
        return (f"--drives {','.join(map(str, drives))}: {node_id} is the simulated EPOS4's own "
                f"node id (--node-id {node_id}); the drives behind its gateway need other ids")
    return None


def _probability(text: str) -> float:
    value = parse_float(text)
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"a probability is between 0 and 1, got {text}")
    return value


def _node_id(text: str) -> int:
    node = parse_int(text)
    if not 1 <= node <= 127:
        raise argparse.ArgumentTypeError(f"node ids are 1..127, got {node}")
    return node


def _milliseconds(text: str) -> float:
    value = parse_float(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"a delay is a non-negative number of ms, got {text}")
    return value


def _node_list(text: str) -> list[int]:
    try:
        nodes = [int(n, 0) for n in text.split(",") if n.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected node ids like 2,3: {text!r}") from None
    if any(not 1 <= n <= 127 for n in nodes):
        raise argparse.ArgumentTypeError("node ids are 1..127")
    twice = sorted({n for n in nodes if nodes.count(n) > 1})
    if twice:
        # Two nodes with one id share its SDO COB-IDs (CiA 301 pre-defined connection
        # set: 600h/580h + node id), so neither could be asked alone.
        raise argparse.ArgumentTypeError(f"node id {twice[0]} appears twice; each drive needs its own")
    return nodes


def _serials(text: str) -> list[str]:
    serials = [s.strip() for s in text.split(",")]
    if not all(serials) or any(not s.isascii() or not s.isprintable() or " " in s or len(s) > 126
                               for s in serials):
        raise argparse.ArgumentTypeError(f"expected serial numbers like 1234 or 1234,5678: {text!r}")
    if len(set(serials)) != len(serials) or len(serials) > 8:
        raise argparse.ArgumentTypeError("up to 8 different serial numbers")
    return serials


def _slave_count(text: str) -> int:
    try:
        count = int(text)
    except ValueError:
        count = 0
    if not 1 <= count <= 64:
        raise argparse.ArgumentTypeError(f"a number of slaves is 1..64, got {text!r}")
    return count


def add_arguments(parser: argparse.ArgumentParser) -> None:
    where = parser.add_mutually_exclusive_group()
    where.add_argument("--pty", action="store_true", help="serve on a pseudo-terminal (default)")
    where.add_argument("--tcp", type=_host_port, metavar="HOST:PORT",
                       help="serve on TCP (reach it with socket://HOST:PORT); port 0 picks one")
    where.add_argument("--usb", action="store_true",
                       help="appear as USB device 24E7:3B01 on a umockdev testbed (reach it with "
                            "usb:// under umockdev-wrapper; needs Debian's umockdev, "
                            "gir1.2-umockdev-1.0, python3-gi)")
    where.add_argument("--ethercat", metavar="IFACE",
                       help="serve simulated EPOS4 drives as EtherCAT slaves on network "
                            "interface IFACE (raw socket: root or CAP_NET_RAW; e.g. one end "
                            "of a veth pair, the master on the other)")
    parser.add_argument("--slaves", type=_slave_count, default=1, metavar="N",
                        help="--ethercat: N drives in a line (default 1)")
    parser.add_argument("--quirk", action="append", default=[], metavar="POS:NAME",
                        help="--ethercat: make slave POS differ from a plain EPOS4: no-ca, "
                             "ca-no-pad, no-XXXX (an object it lacks, e.g. no-6067), "
                             "late=SECONDS (store/restore answered late); repeatable")
    parser.add_argument("--events", metavar="FILE",
                        help="--ethercat: append what each drive does in every cycle to FILE "
                             "(JSON lines; for tests)")
    parser.add_argument("--serial", type=_serials, default=None, metavar="SN[,SN...]",
                        help="--usb: the USB serial number; several make several units "
                             "(default SIM00001)")
    parser.add_argument("--node-id", type=_node_id, default=1, metavar="1..127",
                        help="the simulated EPOS4's own node id (default 1)")
    parser.add_argument("--drives", type=_node_list, default=[], metavar="2,3",
                        help="node ids of simulated drives behind the CAN gateway")
    parser.add_argument("--can-server", type=_can_server, metavar="HOST:PORT",
                        help="also serve the simulated CAN bus over the socketcand protocol "
                             "(python-can: interface socketcand, channel can0); port 0 picks "
                             "one; no authentication: keep it on 127.0.0.1 unless you mean it")
    parser.add_argument("--baud", type=baud_rate, default=None, help="pace replies like a UART at N baud")
    parser.add_argument("--drop", type=_probability, default=0.0, metavar="P",
                        help="drop each reply byte with probability P")
    parser.add_argument("--corrupt", type=_probability, default=0.0, metavar="P",
                        help="corrupt each reply byte with probability P")
    parser.add_argument("--delay", type=_milliseconds, default=0.0, metavar="MS",
                        help="delay each reply by MS milliseconds")
    parser.add_argument("--silent", action="store_true", help="read requests, never answer")
    parser.add_argument("--seed", type=int, default=None, help="seed of the fault generator")
    parser.add_argument("--trace", metavar="FILE",
                        help="record the link's traffic to FILE (capture format; TX = host to device)")
    parser.add_argument("-v", "--verbose", action="store_true", help="log protocol events")


def run(args: argparse.Namespace, ready: Optional[threading.Event] = None) -> int:
    if getattr(args, "ethercat", None):
        return _run_ethercat(args, ready)
    if getattr(args, "quirk", None) or getattr(args, "events", None):
        print("epos-link sim: --quirk and --events apply to --ethercat only", file=sys.stderr)
        return 2
    if getattr(args, "slaves", 1) != 1:
        print("epos-link sim: --slaves applies to --ethercat only", file=sys.stderr)
        return 2
    conflict = own_id_conflict(args.node_id, args.drives)
    if conflict:
        print(f"epos-link sim: {conflict}", file=sys.stderr)
        return 2
    from .. import simulator  # noqa: F401  (import cost only for this command)
    from ..simulator.core import Epos4Simulator
    from ..capture import CaptureWriter
    from ..simulator.link import LinkOptions, PtyLink, TcpLink

    if args.serial and not args.usb:
        print("epos-link sim: --serial applies to --usb only", file=sys.stderr)
        return 2
    if args.can_server and args.serial and len(args.serial) > 1:
        print("epos-link sim: --can-server serves one simulator's bus: give one --serial",
              file=sys.stderr)
        return 2
    if args.usb and args.baud:
        print("epos-link sim: --baud paces a UART; it does not apply to --usb", file=sys.stderr)
        return 2
    if args.usb:
        from ..simulator.usb_link import unavailable_reason

        reason = unavailable_reason()
        if reason:
            print(f"epos-link sim: --usb is not available: {reason}", file=sys.stderr)
            return 2

    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(asctime)s %(name)s %(message)s")
    if not args.verbose:
        # An absent node's SDO timeout is an expected answer (0x05040000), not an error to log.
        logging.getLogger("canopen").setLevel(logging.CRITICAL)
    options = LinkOptions(baud=args.baud, drop=args.drop, corrupt=args.corrupt,
                          delay=args.delay / 1000.0, silent=args.silent, seed=args.seed)
    trace_file = None
    trace = None
    if args.trace:
        try:
            trace_file = open(args.trace, "w", encoding="utf-8")
        except OSError as exc:
            print(f"epos-link sim: cannot write the trace {args.trace}: "
                  f"{exc.strerror or exc}", file=sys.stderr)
            return 2
        trace = CaptureWriter(trace_file, comments=["source: epos-link sim (simulated EPOS4), "
                                                    "TX host to device, RX device to host"])
    sims = [Epos4Simulator(args.node_id, args.drives) for _ in (args.serial or ["-"])]
    sim = sims[0]
    can_server = None
    if args.can_server:
        from ..simulator.socketcand import SocketcandServer, listen_error

        try:
            can_server = SocketcandServer(sim.channel, *args.can_server).start()
        except OSError as exc:
            for each in sims:
                each.close()
            if trace_file:
                trace_file.close()
            host, port = args.can_server
            print(f"epos-link sim: --can-server cannot listen on {host}:{port}: "
                  f"{listen_error(exc)}", file=sys.stderr)
            return 2
    link: Any
    try:
        if args.usb:
            from ..simulator.usb_link import UsbLink

            link = UsbLink(sims, args.serial or ["SIM00001"], options, trace=trace)
            where = (", ".join(u.url for u in link.units)
                     + f": run programs as {link.how_to_run}")
        elif args.tcp:
            link = TcpLink(sim, options, host=args.tcp[0], port=args.tcp[1], trace=trace)
            where = link.url
        else:
            link = PtyLink(sim, options, trace=trace)
            where = link.path
    except (OSError, EposError) as exc:
        if can_server is not None:
            can_server.close()
        for each in sims:
            each.close()
        if trace_file:
            trace_file.close()
        where = (f"on {args.tcp[0]}:{args.tcp[1]}" if args.tcp
                 else "as a USB device" if getattr(args, "usb", False) else "on a pty")
        # create_server() folds the address into strerror; name it once, here.
        why = os.strerror(exc.errno) if isinstance(exc, OSError) and exc.errno else exc
        print(f"epos-link sim: cannot listen {where}: {why}", file=sys.stderr)
        return 2
    stop = threading.Event()

    def _stop(*_: object) -> None:
        stop.set()

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _stop)
        signal.signal(signal.SIGINT, _stop)
    link.start()
    if args.usb:
        _control_usb(link, stop)
    print(f"listening on {where}", flush=True)
    if args.drives:
        channels = ", ".join(s.channel for s in sims)
        print(f"drives behind the gateway: {', '.join(map(str, args.drives))} "
              f"(on the in-process python-can virtual channel {channels})", flush=True)
    if can_server is not None:
        print(f"CAN bus served over socketcand at {can_server.url} "
              f"(channel {can_server.bus_name})", flush=True)
    if ready is not None:
        ready.set()
    try:
        while not stop.wait(0.2):
            pass
    finally:
        if can_server is not None:
            can_server.close()
        link.close()
        for each in sims:
            each.close()
        if trace_file:
            trace_file.close()
    return 0


def _control_usb(link: Any, stop: threading.Event) -> None:
    """Unplug and replug on demand: lines on standard input, SIGUSR1/SIGUSR2."""
    lock = threading.Lock()

    def change(action: str, which: Optional[int]) -> None:
        indices = range(len(link.units)) if which is None else [which]
        with lock:
            for i in indices:
                try:
                    unit = link.unplug(i) if action == "unplug" else link.replug(i)
                except (ValueError, EposError) as exc:
                    print(f"{action}: {exc}", file=sys.stderr, flush=True)
                    continue
                where = f" at {unit.devnode}" if unit.plugged else ""
                print(f"{'replugged' if unit.plugged else 'unplugged'} {unit.url}{where}", flush=True)

    def from_stdin() -> None:
        for line in sys.stdin:
            words = line.split()
            if not words:
                continue
            action = {"unplug": "unplug", "replug": "replug", "plug": "replug"}.get(words[0])
            try:
                which = int(words[1]) if len(words) > 1 else None
            except ValueError:
                action = None
            if action is None:
                print(f"unknown command {line.strip()!r}: use 'unplug [N]' or 'replug [N]'",
                      file=sys.stderr, flush=True)
                continue
            change(action, which)
            if stop.is_set():
                return

    if threading.current_thread() is threading.main_thread():
        # Signal handlers only set work for a thread: the change waits on the helper.
        for signum, action in ((signal.SIGUSR1, "unplug"), (signal.SIGUSR2, "replug")):
            signal.signal(signum, lambda *_, a=action: threading.Thread(
                target=change, args=(a, None), daemon=True).start())
    if sys.stdin is not None and not sys.stdin.closed:
        threading.Thread(target=from_stdin, name="epos-sim-usb-control", daemon=True).start()


def _run_ethercat(args: argparse.Namespace, ready: Optional[threading.Event]) -> int:
    """``--ethercat IFACE``: EtherCAT slaves on a raw socket (epos_link.simulator.ethercat)."""
    from ..simulator.ethercat.server import EthercatServer

    from ..simulator.ethercat.quirks import QuirkError, parse_quirks

    if args.drives or args.serial or args.can_server or args.trace or args.baud:
        print("epos-link sim: --ethercat takes only --slaves, --quirk, --events (and -v)",
              file=sys.stderr)
        return 2
    try:
        quirks = parse_quirks(args.quirk, args.slaves)
    except QuirkError as exc:
        print(f"epos-link sim: {exc}", file=sys.stderr)
        return 2
    try:
        server = EthercatServer(args.ethercat, slaves=args.slaves, quirks=quirks,
                                events=args.events)
    except PermissionError:
        print(f"epos-link sim: --ethercat {args.ethercat} needs root or CAP_NET_RAW "
              "(a raw packet socket)", file=sys.stderr)
        return 2
    except OSError as exc:
        why = os.strerror(exc.errno) if exc.errno else str(exc)
        print(f"epos-link sim: cannot serve EtherCAT on {args.ethercat!r}: {why}", file=sys.stderr)
        return 2
    stop = threading.Event()
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, lambda *_: stop.set())
        signal.signal(signal.SIGINT, lambda *_: stop.set())
    print(f"EtherCAT: {args.slaves} simulated EPOS4 slave(s) on {args.ethercat}", flush=True)
    if ready is not None:
        ready.set()
    try:
        while not stop.wait(0.2):
            pass
    finally:
        server.close()
    return 0
