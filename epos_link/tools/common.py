"""What the link commands share: the URL argument, link options, number parsing,
and the one place that turns an exception into a message and an exit code.

Exit codes (see :mod:`epos_link.cli`): 0 success; 1 the device answered with
an error code, printed as ``0x%08X`` with its name; 2 usage errors, timeouts,
unreachable ports, a silent EPOS4 and communication failures. Expected
failures never print a traceback.

A silent link is diagnosed before any node is blamed (:func:`require_device`):
a node behind the EPOS4's gateway that is absent is answered by the gateway
itself, with abort 0x05040000 (guide chapter 5), so no answer at all means the
EPOS4 on the link is silent (wrong port or baud rate, no power). That is
confirmed by asking the EPOS4 itself (node 0) and said in one line naming the
URL and what to check.
"""
from __future__ import annotations

import argparse
import math
import sys
from typing import Callable, Optional

from ..client import DEFAULT_RETRIES, DEFAULT_TIMEOUT, EposClient
from ..transports import silence_hint
from ..errors import (
    DeviceError,
    EposError,
    EposTimeoutError,
    LocalProtocolError,
    RemoteProtocolError,
    TransportError,
)

URL_HELP = ("link URL: a serial device (/dev/ttyUSB0, COM3), usb:// or usb://?serial=SN, "
            "socket://HOST:PORT, rfc2217://HOST:PORT, sim://, replay://CAPTURE.txt, "
            "or any pyserial URL")


def parse_int(text: str) -> int:
    """Decimal or 0x-hex (``300``, ``0x12C``, ``-5``); for argparse ``type=``."""
    t = text.strip().replace("_", "")
    negative = t.startswith("-")
    digits = t[1:] if negative else t
    try:
        if digits[:2].lower() == "0x":
            value = int(digits[2:], 16)
        else:
            value = int(digits, 10)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a decimal or 0x-hex number") from None
    return -value if negative else value


def parse_float(text: str) -> float:
    """A finite decimal number; for argparse ``type=``."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"{text!r} is not a finite number")
    return value


def positive_float(text: str) -> float:
    value = parse_float(text)
    if value <= 0:
        raise argparse.ArgumentTypeError("must be above 0")
    return value


def non_negative_int(text: str) -> int:
    value = parse_int(text)
    if value < 0:
        raise argparse.ArgumentTypeError("must be 0 or more")
    return value


def baud_rate(text: str) -> int:
    value = parse_int(text)
    if not 50 <= value <= 12_000_000:
        raise argparse.ArgumentTypeError(f"baud rate {value} is outside 50..12000000")
    return value


def add_url(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("url", metavar="URL", help=URL_HELP)


def add_link_options(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("link options")
    group.add_argument("--timeout", type=positive_float, default=DEFAULT_TIMEOUT, metavar="SECONDS",
                       help=f"deadline per request (default {DEFAULT_TIMEOUT:g}, the EPOS4 frame timeout)")
    group.add_argument("--retries", type=non_negative_int, default=DEFAULT_RETRIES, metavar="N",
                       help=f"retries after communication errors (default {DEFAULT_RETRIES})")
    group.add_argument("--baud", type=baud_rate, default=None, metavar="BAUD",
                       help="serial baud rate (default 115200)")
    group.add_argument("--gateway-id", type=parse_int, default=None, metavar="NODE",
                       help="the connected EPOS4's own node id (allows segmented writes to it)")
    group.add_argument("--trace", metavar="FILE",
                       help="record the traffic to FILE, - for standard output "
                       "(capture format; replay with replay://FILE)")


# The URL this command opened last (one process, one command): report() words the
# errors whose cause is the URL itself.
_opened: list[str] = []
SDO_TIMED_OUT = 0x05040000  # what the gateway answers for a node nobody simulates or wired


def _sim_without_drives(url: str) -> bool:
    return url.lower().startswith("sim://") and "drives=" not in url


def open_client(args: argparse.Namespace) -> EposClient:
    """The client of the link options; ``--trace -`` traces to standard output."""
    _opened[:] = [str(args.url)]
    to_stdout = args.trace == "-"
    client = EposClient.open(args.url, trace=None if to_stdout else args.trace, baudrate=args.baud,
                             gateway_node_id=args.gateway_id, timeout=args.timeout,
                             retries=args.retries)
    if to_stdout:
        from ..transports.trace import TracingTransport

        client.transport = TracingTransport(client.transport, sys.stdout,
                                            comments=[f"source: epos-link trace of {args.url}"])
    return client


class DeviceSilent(EposTimeoutError):
    """The EPOS4 on the link gave no answer to a read of its own device type (node 0)."""


def require_device(client: EposClient, url: str, baudrate: Optional[int] = None) -> None:
    """Raise :class:`DeviceSilent` unless the EPOS4 on the link answers a read of its
    device type (1000h/00h as node 0: itself, guide chapter 5; CiA 301 7.5.2.1).

    Any answer counts, an error code included. Costs one request when the device
    answers; on a silent link the client's timeout and retries (``--timeout``,
    ``--retries``: 0.5 s and one retry by default, about 2 s with the waits
    for a late answer).
    """
    try:
        client.read_object(0, 0x1000, 0)
    except DeviceError:
        return
    except (EposTimeoutError, RemoteProtocolError) as exc:
        raise device_silent(url, baudrate, exc) from exc


def device_silent(url: str, baudrate: Optional[int], exc: BaseException) -> DeviceSilent:
    """The one line of a silent EPOS4: the URL, what failed, what to check."""
    return DeviceSilent(f"the EPOS4 at {url} does not answer ({exc}): {silence_hint(url, baudrate)}")


def report(prog: str, exc: BaseException) -> int:
    """The message and exit code of an expected failure."""
    if isinstance(exc, DeviceError):
        where = str(exc).rsplit(": ", 1)[0] if ": " in str(exc) else ""
        hint = ""
        if exc.code == SDO_TIMED_OUT and any(_sim_without_drives(u) for u in _opened):
            # The simulated EPOS4 answers for an absent node as the real one does; the
            # cause here is the URL, which asked for no drives behind it.
            hint = ("; sim:// without ?drives= simulates the EPOS4 alone, with no drive "
                    "behind its gateway: give them, e.g. sim://?drives=2,3")
        print(f"{prog}: device error 0x{exc.code:08X} {exc.name}" + (f" ({where})" if where else "")
              + hint, file=sys.stderr)
        return 1
    if isinstance(exc, DeviceSilent):
        print(f"{prog}: {exc}", file=sys.stderr)
    elif isinstance(exc, EposTimeoutError):
        print(f"{prog}: timeout: {exc} (check the URL, cabling, node id and baud rate)", file=sys.stderr)
    elif isinstance(exc, TransportError):
        print(f"{prog}: link error: {exc}", file=sys.stderr)
    elif isinstance(exc, RemoteProtocolError):
        print(f"{prog}: communication error: {exc}", file=sys.stderr)
    elif isinstance(exc, LocalProtocolError):
        print(f"{prog}: {exc}", file=sys.stderr)
    else:
        print(f"{prog}: {type(exc).__name__}: {exc}", file=sys.stderr)
    return 2


def guarded(prog: str, body: Callable[[], int]) -> int:
    """Run ``body``; expected failures become a message and an exit code."""
    try:
        return body()
    except EposError as exc:  # anything else is a bug and keeps its traceback
        return report(prog, exc)


__all__ = ["URL_HELP", "DeviceSilent", "device_silent", "require_device", "add_link_options", "add_url", "guarded", "non_negative_int", "open_client",
           "parse_int", "positive_float", "report"]
