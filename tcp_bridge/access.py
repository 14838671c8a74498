"""Who may connect: the allow-list of client networks (``--allow``, ``[bridge] allow``).

Policy: the bridge moves motors, so it serves only the hosts it was told to.
The list is a tuple of networks in CIDR notation (``10.1.2.0/24``,
``192.168.0.7``, ``::1/128``); a client whose address is in none of them is
closed at once, without a reply, and logged with its address
(:mod:`tcp_bridge.server`). The default is the loopback networks, matching
the default bind address 127.0.0.1; serving other hosts takes an explicit
``--allow`` (``0.0.0.0/0`` and ``::/0`` allow any host, on purpose).

An IPv4 client on a dual-stack IPv6 socket shows up as ``::ffff:a.b.c.d``; it
is matched as the IPv4 address it is. Pure: ``ipaddress`` only.
"""
from __future__ import annotations

import ipaddress
from typing import Any, Final, Iterable, Optional, Tuple, Union

Network = Union[ipaddress.IPv4Network, ipaddress.IPv6Network]
Address = Union[ipaddress.IPv4Address, ipaddress.IPv6Address]

LOOPBACK: Final[Tuple[Network, ...]] = (ipaddress.ip_network("127.0.0.0/8"),
                                        ipaddress.ip_network("::1/128"))


def parse_network(text: Any) -> Network:
    """One CIDR network; ValueError with a message that quotes ``text``.

    Host bits set (``10.1.2.3/24``) are refused rather than silently widened:
    the person who wrote it meant either the host or the network, and a guess
    here could open the bridge to a whole subnet.
    """
    if not isinstance(text, str):
        raise ValueError(f"{text!r} is not a network in CIDR notation (a string such as "
                         "\"10.1.2.0/24\")")
    try:
        return ipaddress.ip_network(text.strip(), strict=True)
    except ValueError as exc:
        raise ValueError(f"{text!r} is not a network in CIDR notation ({exc})") from None


def parse_networks(texts: Iterable[Any]) -> Tuple[Network, ...]:
    return tuple(parse_network(t) for t in texts)


def client_address(peer: Any) -> Optional[Address]:
    """The IP address of a ``peername`` tuple (IPv4-mapped IPv6 as IPv4); None if not IP."""
    if not isinstance(peer, (tuple, list)) or not peer:
        return None
    try:
        address = ipaddress.ip_address(str(peer[0]).split("%", 1)[0])
    except ValueError:
        return None
    if isinstance(address, ipaddress.IPv6Address) and address.ipv4_mapped is not None:
        return address.ipv4_mapped
    return address


def is_allowed(peer: Any, networks: Iterable[Network]) -> bool:
    """True if the client at ``peer`` (a peername tuple) is in one of ``networks``."""
    address = client_address(peer)
    if address is None:
        return False
    return any(address.version == net.version and address in net for net in networks)


def is_loopback_bind(host: str) -> bool:
    """True if listening on ``host`` serves this machine only (a loopback address or name)."""
    if host in ("localhost", "ip6-localhost"):
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def describe(networks: Iterable[Network]) -> str:
    return ", ".join(str(n) for n in networks) or "(none)"
