"""The types of the bus options of the shipped backends, checked when the axis table loads.

A backend reads its options when the bus opens (:mod:`tcp_bridge.backends`), and
some it hands on unread: ``canopen`` passes ``bitrate`` to python-can, whose
``virtual`` interface ignores it, so ``bitrate = "fast"`` used to start a
server; ``epos`` passes ``timeout`` to the client, which failed with a line
that did not name the key (issue 24). So each option whose type is known is
checked here, with the axis table, and a mistake is one line naming the bus and
the key, as every other key of the table (:mod:`tcp_bridge.tables.config`).

Only types are checked: what a backend does with a value (an EDS path, a
python-can interface name, PDO timing) stays its own check. Options not listed
here (``interface``, ``channel`` and the rest of python-can's keywords) are
not checked, and a backend from an entry point has none listed.
"""
from __future__ import annotations

import math
from typing import Any, Callable, Final, Mapping, Optional, Tuple

from epos_link.transports import known_scheme

Check = Tuple[Callable[[Any], bool], str]  # (is it good, what it must be)


def _integer(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


SECONDS: Final[Check] = (lambda v: _number(v) and v > 0, "a positive number of seconds")
MILLISECONDS: Final[Check] = (lambda v: _number(v) and v > 0, "a positive number of milliseconds")
RATE: Final[Check] = (lambda v: _integer(v) and v > 0, "a positive integer (bit/s)")
COUNT: Final[Check] = (lambda v: _integer(v) and v >= 0, "an integer, 0 or more")
NODE: Final[Check] = (lambda v: _integer(v) and 1 <= v <= 127, "a node id 1..127 (CiA 301)")
TEXT: Final[Check] = (lambda v: isinstance(v, str), "a string")
# Issue 35: a mistyped scheme used to start a bus that never answers; it is a mistake
# in the table like any other (epos_link.transports.known_scheme: ours and pyserial's).
URL: Final[Check] = (lambda v: isinstance(v, str) and known_scheme(v),
                     "a device path or a URL of a known scheme (usb://, socket://, "
                     "rfc2217://, sim://, ...)")

# The epos_link client's options (EposClient.open); the sim backend reaches the
# simulator through it, or (link = "can") through the canopen backend.
_EPOS: Final[Mapping[str, Check]] = {
    "url": URL, "baudrate": RATE, "timeout": SECONDS, "retries": COUNT,
    "gateway_node_id": NODE, "eds": TEXT}
_CANOPEN: Final[Mapping[str, Check]] = {
    "bitrate": RATE, "sdo_timeout": SECONDS, "sdo_retries": COUNT, "eds": TEXT}
OPTION_TYPES: Final[Mapping[str, Mapping[str, Check]]] = {
    "canopen": _CANOPEN,
    "epos": _EPOS,
    "sim": {"link": TEXT, "baud": RATE, "timeout": SECONDS, "gateway_timeout": SECONDS,
            "gateway_node_id": NODE, "sdo_timeout": SECONDS, "sdo_retries": COUNT,
            "eds": TEXT},
    # tcp_bridge.backends.ethercat checks the ranges and how the options relate.
    "ethercat": {"interface": TEXT, "cycle_ms": MILLISECONDS, "watchdog_ms": MILLISECONDS,
                 "sdo_timeout": SECONDS, "op_timeout": SECONDS},
}


def option_problem(backend: str, key: str, value: Any) -> Optional[str]:
    """Why ``value`` cannot be option ``key`` of a ``backend`` bus; None if it can (or
    the option's type is not known here)."""
    check = OPTION_TYPES.get(backend, {}).get(key)
    if check is None or check[0](value):
        return None
    return f"must be {check[1]}"

