"""Transports selected by URL, python-can style: a registry of
``scheme -> (module, factory)`` imported only when used, so a missing optional
dependency (pyusb, libusb) breaks only its own scheme.

* ``usb://``, ``usb://?serial=XXXX``  EPOS4 native USB through pyusb
* ``sim://?node_id=1&drives=2,3``    the in-process simulator (tests, demos)
* anything else                      pyserial's ``serial_for_url``: device paths
  (``/dev/ttyUSB0``, ``COM3``), ``socket://``, ``rfc2217://``, ``loop://``, ``spy://``
"""
from __future__ import annotations

import importlib
from typing import Any, Optional

from .base import Transport

# scheme -> "module:factory"; the factory takes (url, **options) and returns a Transport.
REGISTRY: dict[str, str] = {
    "usb": "epos_link.transports.usb:open_usb",
    "sim": "epos_link.simulator.transport:open_sim",
    "replay": "epos_link.transports.replay:open_replay",
}
DEFAULT = "epos_link.transports.serial:open_serial"
DEFAULT_BAUDRATE = 115200  # guide 2.3.2; the serial transport's default (no pyserial import here)


def open_transport(url: str, **options: Any) -> Transport:
    scheme = url.split("://", 1)[0].lower() if "://" in url else ""
    target = REGISTRY.get(scheme, DEFAULT)
    module_name, factory = target.split(":")
    module = importlib.import_module(module_name)
    transport: Transport = getattr(module, factory)(url, **options)
    return transport


def known_scheme(url: str) -> bool:
    """Whether :func:`open_transport` knows how to open ``url``'s scheme: ours, or one
    of pyserial's URL handlers (``serial.urlhandler.protocol_<scheme>``). A URL
    without ``://`` is a device path. Checked without opening anything, so a
    mistyped URL can be told from a device that is not there."""
    if "://" not in url:
        return True
    scheme = url.split("://", 1)[0].lower()
    if scheme in REGISTRY:
        return True
    if not scheme.isidentifier():
        return False
    import importlib.util

    try:
        return importlib.util.find_spec(f"serial.urlhandler.protocol_{scheme}") is not None
    except ImportError:  # no pyserial: nothing but our own schemes
        return False


def silence_hint(url: str, baudrate: Optional[int] = None) -> str:
    """What to check when the device on ``url`` gives no answer at all: one clause.

    A silent link is told apart from absent nodes by asking the EPOS4 itself
    (node 0, guide chapter 5), so this names the link, never a node id.
    """
    if url.lower().startswith("usb://"):
        return "check the USB cable and the EPOS4's power"
    rate = baudrate or DEFAULT_BAUDRATE
    return f"check the port, the baud rate ({rate} Bd, the EPOS4's setting) and its power"


__all__ = ["Transport", "known_scheme", "open_transport", "REGISTRY", "silence_hint"]
