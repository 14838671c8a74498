"""Record names and the CA server's environment, pure (no caproto, no sockets).

* A record is named ``PREFIX`` + the axis's ``epics_name`` (default ``m<AxAddr>``,
  e.g. ``LAB:m2``). EPICS record names are at most 60 characters of letters, digits and
  ``_ - + : [ ] < > ;`` (EPICS Application Developer's Guide, "Record Name"); the
  longest PV served is the name plus ``:StatusProblem``.
* The environment of a CA server (EPICS base's ``rsrv``, caproto alike):
  ``EPICS_CA_SERVER_PORT`` (default 5064, read by caproto itself),
  ``EPICS_CAS_INTF_ADDR_LIST`` (the interfaces to serve; **default here: loopback
  only**, as the PSI ports; caproto's own default would be every interface) and
  ``EPICS_CAS_BEACON_ADDR_LIST`` (where beacons go; default here: 127.0.0.1 while the
  server is on loopback only, since caproto's default, 255.255.255.255, would
  announce a loopback server to the whole network).
"""
from __future__ import annotations

import ipaddress
import re
from typing import Dict, Final, List, Mapping, Optional, Sequence, Tuple

from ..tables.axes import ConfigError

NAME_RE: Final = re.compile(r"[A-Za-z0-9_\-+:\[\]<>;]*")
MAX_RECORD_NAME: Final = 60
LONGEST_SUFFIX: Final = len(":StatusProblem")
BEACON_PORT_DEFAULT: Final = 5065


def check_part(text: object, what: str) -> str:
    """A prefix or an ``epics_name``: characters EPICS allows in record names."""
    if not isinstance(text, str):
        raise ConfigError(f"{what} must be a string such as \"LAB:\", not {text!r}")
    if not NAME_RE.fullmatch(text) or "." in text:
        raise ConfigError(f"{what} {text!r}: only letters, digits and _ - + : [ ] < > ; "
                          "may appear in an EPICS record name")
    return text


def record_name(prefix: str, addr: int, epics_name: Optional[str]) -> str:
    name = prefix + (epics_name if epics_name else f"m{addr}")
    if not name:
        raise ConfigError("an EPICS record name is empty")
    if len(name) + LONGEST_SUFFIX > MAX_RECORD_NAME + LONGEST_SUFFIX or \
            len(name) > MAX_RECORD_NAME:
        raise ConfigError(f"EPICS record name {name!r} is longer than {MAX_RECORD_NAME} "
                          "characters")
    return name


def record_names(prefix: str, axes: Sequence[Tuple[int, Optional[str]]]) -> List[Tuple[int, str]]:
    """(AxAddr, record name) of every axis; a name given twice is a ConfigError."""
    check_part(prefix, "--epics PREFIX")
    seen: Dict[str, int] = {}
    out = []
    for addr, epics_name in axes:
        if epics_name is not None:
            check_part(epics_name, f"[[axis]] AxAddr {addr}: epics_name")
        name = record_name(prefix, addr, epics_name)
        if name in seen:
            raise ConfigError(f"EPICS record name {name!r} is used by axes {seen[name]} and "
                              f"{addr}")
        seen[name] = addr
        out.append((addr, name))
    return out


def _split(text: str) -> List[str]:
    return [part for part in text.replace(",", " ").split() if part]


def interfaces(environ: Mapping[str, str]) -> List[str]:
    """The addresses to serve on: EPICS_CAS_INTF_ADDR_LIST, else 127.0.0.1."""
    given = _split(environ.get("EPICS_CAS_INTF_ADDR_LIST", ""))
    out = []
    for item in given:
        host = item.rsplit(":", 1)[0] if item.count(":") == 1 else item
        try:
            ipaddress.ip_address(host)
        except ValueError:
            raise ConfigError(f"EPICS_CAS_INTF_ADDR_LIST: {item!r} is not an IP address") \
                from None
        out.append(host)
    return out or ["127.0.0.1"]


def loopback_only(addresses: Sequence[str]) -> bool:
    return all(ipaddress.ip_address(a).is_loopback for a in addresses)


def beacon_addresses(environ: Mapping[str, str], served: Sequence[str]
                     ) -> Optional[List[Tuple[str, int]]]:
    """Where beacons go, when this module decides it: 127.0.0.1 while serving loopback
    only and EPICS_CAS_BEACON_ADDR_LIST is unset; None: caproto's rule (the list
    given, and 255.255.255.255 unless EPICS_CAS_AUTO_BEACON_ADDR_LIST=NO)."""
    if environ.get("EPICS_CAS_BEACON_ADDR_LIST", "").strip() or not loopback_only(served):
        return None
    port = environ.get("EPICS_CAS_BEACON_PORT", "").strip()
    try:
        number = int(port) if port else BEACON_PORT_DEFAULT
    except ValueError:
        raise ConfigError(f"EPICS_CAS_BEACON_PORT: {port!r} is not a port number") from None
    return [("127.0.0.1", number)]


def server_port(environ: Mapping[str, str]) -> int:
    """EPICS_CA_SERVER_PORT (5064 unless set); a bad value is a ConfigError."""
    text = environ.get("EPICS_CA_SERVER_PORT", "").strip()
    if not text:
        return 5064
    try:
        port = int(text)
    except ValueError:
        port = -1
    if not 1 <= port <= 65535:
        raise ConfigError(f"EPICS_CA_SERVER_PORT: {text!r} is not a port 1..65535")
    return port
