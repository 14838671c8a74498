"""Every axis as an EPICS Channel Access motor record (issue 33): ``serve --epics PREFIX``.

No IOC to build: the bridge serves the records itself, on caproto (the optional
extra ``epos-link[epics]``), next to the PSI ports. Modules, in the order a put
travels:

* :mod:`.server` (caproto's context: allow-list, loopback, beacons),
* :mod:`.pvs` (the channels of one record; a put hands over to the record),
* :mod:`.axis` (one axis's record, the motion runner: puts become PSI requests
  through :meth:`tcp_bridge.engine.Engine.execute`),
* :mod:`.readback` (its polls, monitors and alarm: readbacks are PSI reads),
* :mod:`.record` and :mod:`.fields` (pure: the motor record's arithmetic and fields),
* :mod:`.names` (pure: record names and the CA server's environment).

Only :mod:`.server` and :mod:`.pvs` import caproto; :func:`missing` says, in one
line, how to install it when it is not there.
"""
from __future__ import annotations

from typing import Optional

INSTALL_HINT = ("--epics needs caproto, the optional extra [epics]: "
                "pip install 'epos-link[epics]' (in a checkout: .venv/bin/pip install -e '.[epics]')")


class PutRefused(ValueError):
    """A CA put the bridge refused (a PSI CAN: a value the command table refuses, or a
    value the record cannot take): the put fails with ECA_PUTFAIL, the record's
    ``-MsgTxt`` says why and the log has one line for it (no traceback)."""


def missing() -> Optional[str]:
    """None when caproto can be imported, else the one line that says how to get it."""
    try:
        import caproto  # noqa: F401
    except ImportError:
        return INSTALL_HINT
    return None
