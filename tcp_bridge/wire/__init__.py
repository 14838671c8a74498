"""PSI spec 2, the wire: line splitting, requests and replies, pure (no I/O).

``lines`` cuts a TCP byte stream into request lines (2.2.1), ``requests`` parses
them strictly (2.2.1, 2.3.1), ``replies`` formats the 30-byte answers after the
outcome is known (2.2.2, 2.3.2); each module's docstring draws its layout.

Invalid requests are answered CAN with whatever header could be recognised,
left to right; a part that could not be recognised is echoed as ``?``, and a
wholly unrecognisable line is answered ``"? ? ?"<CAN><CR>``. Empty lines are not
answered at all (:class:`LineSplitter`).
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
