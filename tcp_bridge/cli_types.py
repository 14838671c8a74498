"""The argument types of ``tcp-bridge`` (:mod:`tcp_bridge.cli`): each checks one option's
text and raises ``argparse.ArgumentTypeError``, which argparse turns into one line
naming the option and exit 2, never a traceback.
"""
from __future__ import annotations

import argparse
import math

from .access import Network, parse_network
from .client import parse_address, refuse_url


def _int(text: str, what: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not {what}") from None


def port(text: str) -> int:
    value = _int(text, "a port (0..65535)")
    if not 0 <= value <= 65535:
        raise argparse.ArgumentTypeError(f"{value} is not a port (0..65535)")
    return value


def optional_port(text: str) -> int:
    value = _int(text, "a port (0..65535, or -1 for none)")
    if not -1 <= value <= 65535:
        raise argparse.ArgumentTypeError(f"{value} is not a port (0..65535, or -1 for none)")
    return value


def positive_int(text: str) -> int:
    value = _int(text, "a positive integer")
    if value < 1:
        raise argparse.ArgumentTypeError(f"{value} is not a positive integer")
    return value


def positive_seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"{text} is not a positive number of seconds")
    return value


def can_server(text: str) -> str:
    from epos_link.simulator.socketcand import parse_address

    try:
        refuse_url(text)
        host, port = parse_address(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"


def network(text: str) -> Network:
    try:
        return parse_network(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def http_address(text: str) -> "tuple[str, int]":
    from .status.http import parse_address

    try:
        refuse_url(text)
        return parse_address(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def address(text: str) -> str:
    """argparse type of ``send``'s HOST:PORT (checked, kept as text for messages)."""
    try:
        parse_address(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text


__all__ = ["address", "can_server", "http_address", "network", "optional_port", "port",
           "positive_int", "positive_seconds"]
