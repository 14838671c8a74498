"""epos_link: maxon EPOS4 USB/RS232 protocol ("MAXON SERIAL V2") in Python.

Layers, bottom up: :mod:`.crc`, :mod:`.framing`, :mod:`.messages` and
:mod:`.segmented` are pure (bytes in, typed objects out); :mod:`.transports`
move bytes; :class:`EposClient` adds clocks, retries and locks;
:func:`connect_node` puts canopen's own SDO interface on top.
"""
from __future__ import annotations

from typing import Any

__version__ = "0.1.0"

__all__ = ["EposClient", "connect_node", "__version__"]


def __getattr__(name: str) -> Any:
    # Imported on first use, so `import epos_link.framing` stays free of
    # serial/canopen imports (the sans-I/O modules must not pull them in).
    if name == "EposClient":
        from .client import EposClient

        return EposClient
    if name == "connect_node":
        from .canopen_adapter import connect_node

        return connect_node
    raise AttributeError(f"module 'epos_link' has no attribute {name!r}")
