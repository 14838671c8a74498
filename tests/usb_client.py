"""A USB client program, run by the USB tests under ``umockdev-wrapper`` as a user's
program would be: real pyusb, real libusb (``EPOS_LINK_LIBUSB`` picks which).

``python usb_client.py SCENARIO [URL]`` prints one JSON object per line.
Scenarios:

* ``list``: the EPOS4 units that ``epos-link ports`` would list;
* ``access URL``: ReadObject on the EPOS4 and on node 2 behind its gateway, a
  segmented read, a segmented write read back, WriteObject read back, an absent
  object (its abort code);
* ``late URL``: a read that times out (the simulator answers late), then reads
  that must get their own answers, never the late one;
* ``poll URL``: reads 0x1000 and 0x1018/1 every 20 ms and prints each result
  until standard input closes (bounded to 120 s); a value that is not the
  expected one is printed as ``wrong``.
"""
from __future__ import annotations

import json
import select
import sys
import time
from typing import Any

from epos_link.client import EposClient
from epos_link.errors import DeviceError, EposError
from epos_link.transports.usb import list_usb_devices

DEVICE_TYPE = (0x1000, 0)
VENDOR_ID = (0x1018, 1)
POLL_PERIOD = 0.02
POLL_LIMIT = 120.0


def emit(**fields: Any) -> None:
    print(json.dumps(fields), flush=True)


def u32(data: bytes) -> int:
    return int.from_bytes(data[:4], "little")


def scenario_list() -> None:
    emit(units=[{"serial": d.serial, "bus": d.bus, "address": d.address, "url": d.url}
                for d in list_usb_devices()])


def scenario_access(url: str) -> None:
    with EposClient.open(url, timeout=2.0) as client:
        emit(step="device_type", value=u32(client.read_object(0, *DEVICE_TYPE)))
        emit(step="remote_device_type", value=u32(client.read_object(2, *DEVICE_TYPE)))
        emit(step="name", value=client.upload(0, 0x1008, 0).decode())
        emit(step="remote_name", value=client.upload(2, 0x1008, 0).decode())
        client.download(0, 0x30B0, 0, (1234).to_bytes(4, "little"))  # segmented write
        emit(step="downloaded", value=u32(client.upload(0, 0x30B0, 0)))
        client.write_object(0, 0x30B0, 0, (-5).to_bytes(4, "little", signed=True))
        emit(step="home_position",
             value=int.from_bytes(client.read_object(0, 0x30B0, 0), "little", signed=True))
        try:
            client.read_object(0, 0x1234, 0)
            emit(step="absent", error=None)
        except DeviceError as exc:
            emit(step="absent", error=type(exc).__name__, code=exc.code)


def scenario_late(url: str) -> None:
    with EposClient.open(url, timeout=2.0, retries=0, late_answer_timeout=2.0) as client:
        expected = {DEVICE_TYPE: u32(client.read_object(0, *DEVICE_TYPE)),
                    VENDOR_ID: u32(client.read_object(0, *VENDOR_ID))}
        emit(step="ready")
        sys.stdin.readline()  # the test slows the simulator down now
        try:
            client.read_object(0, *DEVICE_TYPE, timeout=0.05)
            emit(step="timeout", error=None)
        except EposError as exc:
            emit(step="timeout", error=type(exc).__name__)
        emit(step="timed_out")
        sys.stdin.readline()  # the test makes the simulator quick again
        # The late answer to 0x1000 is on its way or queued: each read must
        # still get its own object's value.
        for key in (VENDOR_ID, DEVICE_TYPE, VENDOR_ID):
            value = u32(client.read_object(0, *key))
            emit(step="after", object=f"{key[0]:04X}/{key[1]}", value=value,
                 ok=value == expected[key])


def scenario_poll(url: str) -> None:
    # The protocol's answers carry no request id: an answer later than the timeout and
    # the late-answer wait together is taken for the next request's (link.py). 0.2 + 0.2 s
    # was once too short at load 10-15 (a 'wrong' value); 10x the unloaded answer time
    # and more is what a loaded machine needs.
    with EposClient.open(url, timeout=0.5, retries=0, late_answer_timeout=2.0) as client:
        expected = {DEVICE_TYPE: u32(client.read_object(0, *DEVICE_TYPE)),
                    VENDOR_ID: u32(client.read_object(0, *VENDOR_ID))}
        end = time.monotonic() + POLL_LIMIT
        n = 0
        while time.monotonic() < end:
            key = (DEVICE_TYPE, VENDOR_ID)[n % 2]
            n += 1
            try:
                value = u32(client.read_object(0, *key))
                emit(poll=n, result="ok" if value == expected[key] else "wrong", value=value)
            except EposError as exc:
                emit(poll=n, result="error", error=type(exc).__name__, message=str(exc)[:200])
            except Exception as exc:  # anything untyped is a failure the test reports
                emit(poll=n, result="untyped", error=type(exc).__name__, message=str(exc)[:200])
            ready, _, _ = select.select([sys.stdin], [], [], POLL_PERIOD)
            if ready and not sys.stdin.readline():
                break  # the test closed our stdin: done


def main(argv: list[str]) -> int:
    scenario = argv[1]
    if scenario == "list":
        scenario_list()
    elif scenario == "access":
        scenario_access(argv[2])
    elif scenario == "late":
        scenario_late(argv[2])
    elif scenario == "poll":
        scenario_poll(argv[2])
    else:
        print(f"unknown scenario {scenario}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
