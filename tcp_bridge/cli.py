"""``tcp-bridge``: serve the PSI gateway protocol, check an axis table, or send requests.

::

    tcp-bridge serve --config axes.toml [--bind ADDR --allow CIDR ...] [--port 1912]
                     [--maintenance-port 1913] [--idle-timeout 60] [--max-connections 64]
                     [--max-per-host 32] [--http HOST:PORT] [--epics PREFIX]
    tcp-bridge serve --simulate [--axes N] [--can-server HOST:PORT] [--ethercat N]
    tcp-bridge check --config axes.toml [--json]     (read-only, tcp_bridge.check)
    tcp-bridge send HOST:PORT "1R10" ["1R12" ...]
    tcp-bridge --version

Expected failures (a bad argument, a port in use, an unknown bind address, a
bad axis table, a refused connection) print one line and exit with status 2
(argparse's errors too: :class:`epos_link.cli_parser.OneLineParser`); ``serve``
opens every socket it listens on before it says "listening on";
``send`` exits 0 when every reply is ACK, 1 otherwise; ``check`` exits 0 when
every axis answers as configured, 1 otherwise. A bus whose adapter or EPOS4
cannot be opened does not stop ``serve``: it is logged, answers NAK and is
opened in the background (:mod:`tcp_bridge.backends.reopen`). A request given to ``send`` with CR or LF inside is several
requests, each printed with its own reply, as the gateway reads it (spec 2.2.1:
one request per CR-terminated line). ``serve`` stops on SIGINT or SIGTERM, finishing the transfers in
flight; a second signal exits at once (status 128 + signal number), waiting
at most a second for the state file.

``serve --simulate --ethercat N`` adds N simulated EPOS4 EtherCAT slaves on a
veth pair (:mod:`tcp_bridge.backends.ethercat_sim`), axes after the CAN ones;
where the machine does not allow it (root, iproute2, pysoem) it prints why and
exits 2, since it was asked for. The slaves stop and the pair is deleted on
every exit, the second signal's included.
"""
from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import signal
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any, Dict, Optional, Sequence

from epos_link.cli_parser import OneLineParser

from .access import LOOPBACK, is_loopback_bind
from .access import describe as describe_networks
from .errors import BridgeError, MalformedReply
from .cli_types import (address, can_server, http_address, network, optional_port, port,
                        positive_int, positive_seconds)
from .client import describe, send, split_requests
from .wire import Status

if TYPE_CHECKING:
    from .server import ServerOptions
    from .tables.axes import AxisTable, Settings

# asyncio and the axis tables (0.15 s of CPU together) are imported by serve's functions
# only: `tcp-bridge send` and `--help` are spawned by many tests and scripts (issue 32).

PROG = "tcp-bridge"
# argparse prints descriptions as they are: plain text, no reST markup.
DESCRIPTION = ("Serve the PSI \"TCP-IP to CANopen gateway\" protocol (rev 2.3) to EPICS and "
               "NICOS, check an axis table against the drives on its buses, record an axis "
               "through a running bridge, or send requests to a gateway.")


def _fail(message: str) -> int:
    print(f"{PROG}: {message}", file=sys.stderr)
    return 2


def _listen_error(exc: OSError) -> str:
    """The OS's words for a failed listen: asyncio's create_server() rewrites strerror
    ("error while attempting to bind on address ..."), and a resolver error (gaierror)
    has a negative errno that os.strerror does not know."""
    if exc.errno and exc.errno > 0:
        return os.strerror(exc.errno)
    return exc.strerror or str(exc)


# --- serve ---------------------------------------------------------------------------


def _table(args: argparse.Namespace) -> AxisTable:
    from .tables.axes import AxisTable, ConfigError, simulated_table
    from .tables.statefile import check_writable

    if args.simulate:
        options = {}
        if args.sim_link:
            options["link"] = args.sim_link
        if args.sim_baud:
            options["baud"] = args.sim_baud
        if args.can_server:
            options["can_server"] = args.can_server
        sim = getattr(args, "ethercat_sim", None)
        table = simulated_table(args.axes, bus_options=options,
                                ethercat_interface=sim.interface if sim else None,
                                ethercat_slaves=sim.slaves if sim else 0)
    else:
        if args.can_server:
            raise ConfigError("--can-server serves the simulated CAN bus: it needs --simulate")
        table = AxisTable.load(args.config)
    changes: Dict[str, Any] = {}
    if args.debug:
        changes["debug"] = True
    if args.state_file is not None:
        path = Path(args.state_file)
        try:
            check_writable(path)
        except OSError as exc:
            raise ConfigError(f"--state-file {path} cannot be written "
                              f"({exc.strerror or exc})") from None
        changes["state_file"] = path
    if args.allow:
        changes["allow"] = tuple(args.allow)
    if args.idle_timeout is not None:
        changes["idle_timeout"] = args.idle_timeout
    if changes:
        table = dataclasses.replace(table, settings=dataclasses.replace(table.settings, **changes))
    return table


def _server_options(args: argparse.Namespace, settings: Settings) -> "ServerOptions":
    from .tables.axes import ConfigError
    from .server import DEFAULT_IDLE_TIMEOUT, ServerOptions

    allow = settings.allow if settings.allow is not None else LOOPBACK
    if settings.allow is None and not is_loopback_bind(args.bind):
        # Listening on a network interface with the default (loopback-only)
        # allow-list would refuse every client that interface exists for.
        raise ConfigError(f"--bind {args.bind} serves other hosts: say which with --allow CIDR "
                          "(or [bridge] allow); --allow 0.0.0.0/0 allows any IPv4 host")
    ports = [args.port] + ([args.maintenance_port] if args.maintenance_port >= 0 else [])
    idle = settings.idle_timeout if settings.idle_timeout is not None else DEFAULT_IDLE_TIMEOUT
    if args.max_per_host is not None and args.max_per_host > args.max_connections:
        raise ConfigError(f"--max-per-host {args.max_per_host} is more than --max-connections "
                          f"{args.max_connections}")
    return ServerOptions(host=args.bind, ports=ports, max_connections=args.max_connections,
                         idle_timeout=idle, allow=allow, max_per_host=args.max_per_host)


async def _serve(args: argparse.Namespace) -> int:
    import asyncio

    from .engine import build_engine
    from .server import BridgeServer
    from .tables.axes import ConfigError

    table = _table(args)
    options = _server_options(args, table.settings)
    if args.http is not None and tuple(options.allow) == LOOPBACK \
            and not is_loopback_bind(args.http[0]):
        raise ConfigError(f"--http {args.http[0]} serves other hosts: say which with --allow "
                          "CIDR (or [bridge] allow)")
    ports = list(options.ports)
    # Every listening socket is open before "listening on" is printed: a
    # --can-server's socketcand server (with its bus, in build_engine), the PSI
    # ports, then --http. One that cannot be opened is one line, exit 2, after
    # what was opened before it is closed (the engine closes its buses).
    engine = await asyncio.get_running_loop().run_in_executor(None, build_engine, table)
    server = BridgeServer(engine, options)
    try:
        await server.start()
    except OSError as exc:
        engine.close()
        return _fail(f"cannot listen on {args.bind} port {'/'.join(map(str, ports))}: "
                     f"{_listen_error(exc)}")
    status = None
    if args.http is not None:  # the live status page (tcp_bridge.status)
        from .status.http import open_status_page

        try:
            status = await open_status_page(engine, *args.http, allow=options.allow)
        except OSError as exc:
            await server.close()
            return _fail(f"--http: cannot listen on {args.http[0]} port {args.http[1]}: "
                         f"{_listen_error(exc)}")
    epics = None
    prefix = args.epics if args.epics is not None else table.epics_prefix
    if prefix is not None:  # Channel Access motor records (tcp_bridge.epics, issue 33)
        from .epics import missing
        from .epics.names import check_part

        why = missing()
        try:
            if why is not None:
                raise ConfigError(why)
            check_part(prefix, "--epics PREFIX")
            from .epics.server import open_epics

            epics = await open_epics(engine, prefix, allow=options.allow)
        except (ConfigError, OSError) as exc:
            if status is not None:
                await status.close()
            await server.close()
            return _fail(str(exc) if isinstance(exc, ConfigError) else f"--epics: {exc}")
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()

    def on_signal(signum: int) -> None:
        if not stop.is_set():
            stop.set()
            return
        # Second signal: do not wait for transfers in flight (a stuck bus could
        # take minutes); only give the state file writer a moment.
        print(f"{PROG}: second signal; exiting now, transfers in flight are abandoned",
              file=sys.stderr, flush=True)
        engine.params.flush(1.0)
        sim = getattr(args, "ethercat_sim", None)
        if sim is not None:  # os._exit skips main's finally: no slaves or veth left behind
            sim.close(timeout=1.0)
        os._exit(128 + signum)

    for sig in (signal.SIGINT, signal.SIGTERM):
        try:
            loop.add_signal_handler(sig, on_signal, sig)
        except (NotImplementedError, RuntimeError):  # pragma: no cover - Windows
            pass
    names = ["NICOS/EPICS", "maintenance"]
    where = ", ".join(f"{h}:{p} ({names[i] if i < 2 else 'extra'})"
                      for i, (h, p) in enumerate(server.addresses))
    axes = ", ".join(f"{a.addr}={a.bus}/{a.node_id}" for a in table.axes.values())
    print(f"{PROG}: listening on {where}; axes {axes or '(none)'}; clients from "
          f"{describe_networks(options.allow)}", flush=True)
    for backend in engine.backends:
        served = getattr(backend, "can_server", None)
        if served is not None:
            print(f"{PROG}: CAN bus served over socketcand at {served.url} "
                  f"(channel {served.bus_name})", flush=True)
    sim = getattr(args, "ethercat_sim", None)
    if sim is not None:
        print(f"{PROG}: {sim.slaves} simulated EtherCAT slave(s) on veth {sim.peer}, "
              f"the master on {sim.interface}", flush=True)
    if status is not None:
        print(f"{PROG}: status page at {status.url}", flush=True)
    if epics is not None:
        print(f"{PROG}: {epics.describe()}", flush=True)
    await stop.wait()
    print(f"{PROG}: shutting down (a second signal exits at once)", flush=True)
    if epics is not None:
        await epics.close()
    if status is not None:
        await status.close()
    await server.close()
    return 0


# --- send ----------------------------------------------------------------------------


def _send(args: argparse.Namespace) -> int:
    try:
        requests = split_requests(args.request)
        if not requests:
            return _fail("no request to send (every argument is empty)")
        for r in requests:
            if not r.isascii():
                return _fail(f"request {r!r} is not ASCII (the gateway's requests are ASCII, "
                             "spec 2.2.1)")
        replies = send(args.address, requests, args.timeout)
    except (ValueError, UnicodeError) as exc:
        return _fail(str(exc))
    except (OSError, MalformedReply) as exc:
        return _fail(f"{args.address}: {exc.strerror if isinstance(exc, OSError) and exc.strerror else exc}")
    for reply in replies:
        print(describe(reply))
    return 0 if all(r.status is Status.ACK for r in replies) else 1


# --- main ----------------------------------------------------------------------------


COMMANDS = ("serve", "check", "record", "send")


def chosen_command(argv: Sequence[str]) -> Optional[str]:
    """The subcommand ``argv`` names: its first word that is not an option (the top-level
    parser's only option, --version, takes no value), if it is a command."""
    first = next((a for a in argv if not a.startswith("-")), None)
    return first if first in COMMANDS else None


class _Version(argparse.Action):
    """``--version``, looked up only when asked: importlib.metadata costs every spawned
    ``tcp-bridge`` 0.15 s of CPU otherwise (issue 32)."""

    def __init__(self, option_strings: Sequence[str], dest: str = argparse.SUPPRESS,
                 default: str = argparse.SUPPRESS,
                 help: str = "show program's version number and exit") -> None:
        super().__init__(option_strings, dest=dest, default=default, nargs=0, help=help)

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace,
                 values: object, option_string: Optional[str] = None) -> None:
        print(f"{parser.prog} {version()}")  # stdout, as argparse's own action
        parser.exit()


def parser(argv: Optional[Sequence[str]] = None) -> argparse.ArgumentParser:
    """The parser; ``check``'s and ``record``'s arguments (whose modules import canopen,
    python-can and the recorder) are added only when ``argv`` names that command
    (``None``: every command's), so a spawned ``tcp-bridge serve`` or ``send`` does not
    pay 0.3 s of CPU for them (issue 32, as epos_link.cli.build_parser)."""
    wanted = set(COMMANDS) if argv is None else {chosen_command(argv)}
    p = OneLineParser(prog=PROG, description=DESCRIPTION)
    p.add_argument("--version", action=_Version)
    sub = p.add_subparsers(dest="command", required=True)
    s = sub.add_parser("serve", help="serve the PSI gateway protocol (spec rev 2.3)")
    src = s.add_mutually_exclusive_group(required=True)
    src.add_argument("--config", metavar="FILE", help="axis table (TOML), see example_axes.toml")
    src.add_argument("--simulate", action="store_true",
                     help="simulated EPOS4 drives: axis 1 the EPOS4, the rest behind its gateway")
    s.add_argument("--axes", type=int, default=3, metavar="N",
                   help="with --simulate: the EPOS4 itself and N-1 drives behind its gateway (default 3)")
    s.add_argument("--can-server", type=can_server, metavar="HOST:PORT",
                   help="with --simulate: also serve the simulated CAN bus over the socketcand "
                        "protocol (python-can interface socketcand, channel can0); port 0 "
                        "picks one")
    s.add_argument("--ethercat", type=positive_int, metavar="N",
                   help="with --simulate: also N simulated EPOS4 EtherCAT slaves on a veth "
                        "pair, axes after the CAN ones (needs root, iproute2 and pysoem)")
    s.add_argument("--sim-link", choices=["inprocess", "pty"], help=argparse.SUPPRESS)
    s.add_argument("--sim-baud", type=int, help=argparse.SUPPRESS)
    s.add_argument("--bind", default="127.0.0.1", metavar="ADDR",
                   help="address to listen on (default 127.0.0.1; 0.0.0.0 for all, "
                        "with --allow)")
    s.add_argument("--port", type=port, default=1912,
                   help="NICOS/EPICS port (default 1912; 0: any free port)")
    s.add_argument("--maintenance-port", type=optional_port, default=1913,
                   help="maintenance port (default 1913; -1: none)")
    s.add_argument("--max-connections", type=positive_int, default=64, metavar="N",
                   help="simultaneous clients (default 64); when all are taken, a new "
                        "client takes the slot of one idle or silent longest, never of one "
                        "that sent a request in the last 10 s")
    s.add_argument("--max-per-host", type=positive_int, default=None, metavar="N",
                   help="connections one client host may hold (default: half of "
                        "--max-connections); at the cap its newcomers only displace its "
                        "own idle connections")
    s.add_argument("--idle-timeout", type=positive_seconds, default=None, metavar="SECONDS",
                   help="close a connection that sent no request for this long; bytes that "
                        "do not complete a request do not count (default 60, or [bridge] "
                        "idle_timeout)")
    s.add_argument("--allow", type=network, action="append", metavar="CIDR",
                   help="serve clients from this network, e.g. 10.1.2.0/24 (repeatable; "
                        "default: [bridge] allow, else loopback only); others are closed "
                        "unanswered and logged")
    s.add_argument("--http", type=http_address, metavar="HOST:PORT",
                   help="also serve a read-only live status page and its JSON (/api/axes) "
                        "on this address (PORT alone: 127.0.0.1; off unless given)")
    s.add_argument("--epics", metavar="PREFIX",
                   help="also serve every axis as an EPICS Channel Access motor record "
                        "PREFIX+m<AxAddr> (or [epics] prefix); needs the [epics] extra; "
                        "loopback only unless EPICS_CAS_INTF_ADDR_LIST says otherwise")
    s.add_argument("--state-file", metavar="FILE", help="where S-command parameters persist")
    s.add_argument("--debug", action="store_true", help="start with command 91 (debug print) on")
    s.add_argument("-v", "--verbose", action="count", default=0,
                   help="log connections and the bridge's own steps; -vv adds canopen's "
                        "lines (SDO client and, with --simulate, the drives' SDO server)")
    c = sub.add_parser("check", help="read-only pre-flight: does every axis answer as configured?",
                       description="Read each configured drive's name, identity, CiA 402 state, "
                                   "mode, position and units, compare them with the axis table, "
                                   "print one row per axis with its verdict. Writes nothing to "
                                   "any drive. Exit 0 when every axis answers as configured, "
                                   "1 otherwise.")
    if "check" in wanted:
        from .check import add_arguments as check_arguments
        check_arguments(c)
    r = sub.add_parser("record", help="record an axis through a running bridge (PSI reads) "
                       "to CSV and plots",
                       description="Sample readable commands of one axis through a running "
                                   "bridge, as any PSI client reads them (never a second SDO "
                                   "client of the drive), with epos-link record's triggers, "
                                   "CSV and plots. Example: tcp-bridge record 127.0.0.1:1913 2 "
                                   "--trigger move --duration 2 --csv move.csv")
    if "record" in wanted:
        from .record import add_arguments as record_arguments
        record_arguments(r)
    t = sub.add_parser("send", help="send requests to a gateway and print the replies")
    t.add_argument("address", metavar="HOST:PORT", type=address)
    t.add_argument("request", nargs="+",
                   help='e.g. "1R10" or "3S02=12"; CR or LF inside one separates requests')
    t.add_argument("--timeout", type=positive_seconds, default=10.0, metavar="SECONDS",
                   help="bound for connecting and for each reply (default 10)")
    return p


def version() -> str:
    """The installed package version and the PSI protocol revision served."""
    from importlib import metadata

    try:
        installed = metadata.version("epos-link")
    except metadata.PackageNotFoundError:  # pragma: no cover - a bare checkout
        installed = "0+unknown"
    return f"{installed} (PSI TCP-IP to CANopen gateway protocol rev 2.3)"


# Libraries whose own lines the bridge already says in its words (its NAK reasons at
# -v, its bus-silence lines): shown only at -vv.
QUIET_LIBRARIES = (
    # canopen logs an absent node's SDO timeout as an error ("Transfer aborted by
    # client"); at -v its INFO lines would drown the bridge's (147 of 152 at start-up,
    # the simulated drives' SDO server among them).
    "canopen",
    # python-can's socketcand interface warns of every frame it cannot parse and of
    # each failed receive or connection (issue 34: its chatter reached the log at the
    # default level); a bus that stops answering is the bridge's own warning.
    "can.interfaces.socketcand",
)


# The bridge's own loggers whose INFO lines show without -v: the SDO client's, and the
# summaries a bus logs when it closes (the EtherCAT cycle's counts; issue 34: they needed -v).
ALWAYS_INFO = ("tcp_bridge.debug", "tcp_bridge.bus.sdo", "tcp_bridge.summary")


def configure_logging(verbose: int, debug: bool = False) -> None:
    level = logging.INFO if verbose or debug else logging.WARNING
    logging.basicConfig(level=level, format="%(asctime)s %(name)s: %(message)s")
    for name in ALWAYS_INFO:
        logging.getLogger(name).setLevel(logging.INFO)
    for name in QUIET_LIBRARIES:
        logging.getLogger(name).setLevel(logging.CRITICAL if verbose < 2 else logging.NOTSET)


def main(argv: Optional[Sequence[str]] = None) -> int:
    if argv is None:
        argv = sys.argv[1:]
    args = parser(argv).parse_args(argv)
    if args.command == "send":
        return _send(args)
    if args.command == "record":
        from .record import run as run_record

        return run_record(args)
    if args.command == "check":
        from .check import run as run_check

        return run_check(args, prog=f"{PROG} check")
    configure_logging(args.verbose, args.debug)
    sim = None
    if args.ethercat is not None:
        from .backends.ethercat_sim import start

        if not args.simulate:
            return _fail("--ethercat adds simulated EtherCAT slaves: it needs --simulate")
        try:
            sim = args.ethercat_sim = start(args.ethercat)
        except RuntimeError as exc:
            return _fail(f"--ethercat {exc}")
    import asyncio

    from .tables.axes import ConfigError

    try:
        return asyncio.run(_serve(args))
    except (ConfigError, BridgeError) as exc:
        return _fail(str(exc))
    except KeyboardInterrupt:  # a second Ctrl-C during shutdown
        return 130
    finally:
        if sim is not None:  # after the engine closed: the axes stopped, then the slaves
            sim.close()


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
