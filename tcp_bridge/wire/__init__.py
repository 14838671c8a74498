"""PSI spec 2, the wire: line splitting, requests and replies, pure (no I/O).

``lines`` cuts a TCP byte stream into request lines, ``requests`` parses them,
``replies`` formats the 30-byte answers after the outcome is known.

Requests, client -> gateway (spec 2.2.1 and 2.3.1)::

    write:  <axis> S|s <cmd> = <value> CR     33 53 30 32 3D 31 32 0D   "3S02=12"
    read:   <axis> R|r <cmd> CR               33 52 30 32 0D            "3R02"

    axis  1..60, one or two decimal digits         (spec 3: up to 60 axes)
    cmd   one or two decimal digits, "02" == "2"   (spec 4: two-digit table)
    value decimal ([+-]digits[.digits]) or 0x-hex; kept as text, the command
          layer (tcp_bridge.tables.units.parse_value) decides what it means

Replies, gateway -> client, always exactly 30 bytes (spec 2.2.2 and 2.3.2)::

    +------+----+-----+----+-----+----------+--------+----+------------+
    | axis | SP | S/R | SP | cmd | [=value] | status | CR | NUL ... 30 |
    +------+----+-----+----+-----+----------+--------+----+------------+
    "3 S 2"      ACK CR + 23 NUL   33 20 53 20 32 06 0D 00 ...   (2.2.2)
    "3 R 2=12.8" ACK CR + 18 NUL   33 20 52 20 32 3D 31 32 2E 38 06 0D 00 ...
    status: ACK 0x06 executed, NAK 0x15 not executed, CAN 0x18 not valid

The command number is echoed without leading zeros, as in the byte tables of
2.2.2 and 2.3.2 (the prose example "3 S 02" disagrees; the tables are exact,
and :func:`decode_reply` accepts both).

Invalid requests are answered CAN with whatever header could be recognised,
left to right; a part that could not be recognised is echoed as ``?``. The spec
has no rule for this case, and a client waiting for one reply per request must
get one, so a wholly unrecognisable line is answered ``"? ? ?"<CAN><CR>``.
Empty lines are not answered at all (see :class:`LineSplitter`).
"""
from .lines import DEFAULT_MAX_LINE, LineSplitter
from .replies import (CR, MAX_VALUE_LEN, REPLY_SIZE, Reply, Status, decode_reply,
                      format_error_reply, format_read_reply, format_read_status,
                      format_status_reply, format_value, format_write_reply, status_for)
from .requests import (MAX_AXIS, NUMBER_RE, Header, Line, ReadRequest, Request, WriteRequest,
                       format_request, parse_item, parse_request, recognise_header)

__all__ = ["CR", "DEFAULT_MAX_LINE", "Header", "Line", "LineSplitter", "MAX_AXIS",
           "MAX_VALUE_LEN", "NUMBER_RE", "REPLY_SIZE", "ReadRequest", "Reply", "Request",
           "Status", "WriteRequest", "decode_reply", "format_error_reply", "format_read_reply",
           "format_read_status", "format_request", "format_status_reply", "format_value",
           "format_write_reply", "parse_item", "parse_request", "recognise_header", "status_for"]
