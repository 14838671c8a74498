"""How long CAN frames take on the simulated bus (the python-can virtual bus takes none).

A python-can ``virtual`` bus hands a frame to every listener the instant it is
sent. A real CAN bus carries it bit by bit. A simulated drive therefore answers an
SDO no sooner than a real one could: after the request has been on the wire, and
with its answer on the wire after that (the client has it at the end of the
frame). The simulated drive's own processing time is taken as zero (not found in
a public maxon source), so the simulator is still at least as fast as a device.

Frame length (ISO 11898-1, CAN 2.0A data frame): SOF 1, identifier 11, RTR 1,
IDE 1, r0 1, DLC 4, data 8 per byte, CRC 15, CRC delimiter 1, ACK slot and
delimiter 2, EOF 7 bits, then 3 bits of intermission before the next frame.
Stuff bits are not counted: a frame has at least none. An SDO frame always carries
8 data bytes (CiA 301 7.2.4.3), so 111 bit times.

The bit rate defaults to 1 Mbit/s, the fastest of the standard CANopen bit
timing table (CiA 305 LSS table index 0 = 1000 kbit/s, as device manuals quote
it, e.g. the KS 800 CANopen interface manual 7.6.3): the most lenient choice.
"""
from __future__ import annotations

import time
from typing import Final, Optional

DEFAULT_BITRATE: Final = 1_000_000  # bit/s
SDO_FRAME_BYTES: Final = 8  # CiA 301: every SDO frame has 8 data bytes


def frame_time(data_bytes: int, bitrate: int) -> float:
    """Seconds a CAN 2.0A data frame with ``data_bytes`` occupies the bus, intermission included."""
    if not 0 <= data_bytes <= 8:
        raise ValueError(f"a CAN frame carries 0..8 data bytes, not {data_bytes}")
    return (47 + 8 * data_bytes) / bitrate


def sdo_answer_due(sent_at: float, request_bytes: int, bitrate: Optional[int]) -> float:
    """When the answer to an SDO request sent at ``sent_at`` (``time.time()``) can have
    reached its client: the request's frame, then the answer's (None: at once)."""
    if bitrate is None:
        return sent_at
    return sent_at + frame_time(request_bytes, bitrate) + frame_time(SDO_FRAME_BYTES, bitrate)


def wait_until(due: float) -> None:
    """Sleep until ``time.time()`` reaches ``due`` (the clock of python-can's timestamps)."""
    delay = due - time.time()
    if delay > 0:
        time.sleep(delay)


__all__ = ["DEFAULT_BITRATE", "frame_time", "sdo_answer_due", "wait_until"]
