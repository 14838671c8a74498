"""A PSI gateway client: send requests to a bridge (or a MasterMACS) and decode the replies.

``tcp-bridge send`` (:mod:`tcp_bridge.cli`) is this module on the command line;
tests and the status page's callers use :func:`send` directly. Each request
goes out with CR appended (spec 2.2.1) and its reply is the fixed 30 bytes of
spec 2.2.2, decoded by :func:`tcp_bridge.wire.decode_reply`.
"""
from __future__ import annotations

import re
import socket
from typing import List, Sequence
from urllib.parse import urlsplit

from .errors import MalformedReply
from .wire import REPLY_SIZE, Reply, decode_reply


def describe(reply: Reply) -> str:
    """``"1 R 10=567 ACK"``: the reply with its status spelled out."""
    head = " ".join("?" if p is None else str(p) for p in (reply.axis, reply.kind, reply.cmd))
    value = "" if reply.value is None else f"={reply.value}"
    return f"{head}{value} {reply.status.name}"


SCHEME = re.compile(r"[A-Za-z][A-Za-z0-9+.-]*://")  # RFC 3986 3.1, then "//" authority


def refuse_url(text: str) -> None:
    """ValueError for ``http://HOST:PORT``, ``socket://...``, ``tcp://...``: a HOST:PORT
    option given a URL. Left alone, ``rpartition(":")`` would take ``http://HOST`` for
    the host, and the resolver's "Name or service not known" would hide the mistake."""
    if not SCHEME.match(text):
        return
    hint = ""
    try:
        parts = urlsplit(text)
        if parts.port is not None:
            host = parts.hostname or "127.0.0.1"
            hint = f" (did you mean {'[' + host + ']' if ':' in host else host}:{parts.port}?)"
    except ValueError:  # a port that is not a number: no suggestion
        pass
    raise ValueError(f"expected HOST:PORT, not a URL{hint}")


def parse_address(text: str) -> tuple[str, int]:
    refuse_url(text)
    host, sep, port = text.rpartition(":")
    if not sep or not port.isdigit():
        raise ValueError(f"expected HOST:PORT, not {text!r}")
    if not 1 <= int(port) <= 65535:
        raise ValueError(f"{text!r}: port {int(port)} is not 1..65535")
    return host.strip("[]") or "127.0.0.1", int(port)


def split_requests(texts: Sequence[str]) -> List[str]:
    """Each argument's CR- or LF-separated lines, stripped, empty ones dropped.

    The gateway ends a request at CR (spec 2.2.1), and our server at LF too, so
    ``"1R10\\n1R12"`` is two requests with two replies; sending it as one
    would print the first reply and leave the second unread.
    """
    out: List[str] = []
    for text in texts:
        out.extend(line.strip() for line in text.replace("\r", "\n").split("\n"))
    return [line for line in out if line]


NOT_PSI = ("it answered in HTTP: that is a web server (the bridge's --http status page?), "
           "not a PSI port; the bridge serves PSI on 1912 and 1913 (serve --port)")


def send(address: str, requests: Sequence[str], timeout: float = 10.0) -> List[Reply]:
    """Send each request (CR appended) and decode its 30-byte reply."""
    host, port = parse_address(address)
    requests = split_requests(requests)
    replies = []
    with socket.create_connection((host, port), timeout=timeout) as sock:
        for text in requests:
            sock.sendall(text.encode("ascii") + b"\r")
            data = b""
            while len(data) < REPLY_SIZE:
                chunk = sock.recv(REPLY_SIZE - len(data))
                if chunk.startswith(b"HTTP/") or data.startswith(b"HTTP/"):
                    raise MalformedReply(f"{address}: {NOT_PSI}")
                if not chunk:
                    raise MalformedReply(f"connection closed after {len(data)} bytes of a reply")
                data += chunk
            if data.startswith(b"HTTP/"):
                raise MalformedReply(f"{address}: {NOT_PSI}")
            replies.append(decode_reply(data))
    return replies


__all__ = ["describe", "parse_address", "refuse_url", "send", "split_requests"]
