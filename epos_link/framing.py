r"""Frames of MAXON SERIAL V2: encoding and a resynchronising stream decoder.

Guide 2.2.2 (frame structure) and 2.2.4 (character stuffing)::

    +------+------+--------+-----+---------------------+---------+
    | DLE  | STX  | OpCode | Len | Data[0..Len-1]      | CRC     |
    | 0x90 | 0x02 | BYTE   | BYTE| Len words, LSB first| WORD LE |
    +------+------+--------+-----+---------------------+---------+
                  \________ stuffed: every 0x90 doubled ________/

Recovery cases of :class:`FrameDecoder` (each raises once, then the decoder
continues from the point after the bad bytes, so no later frame is lost):

* bytes before a DLE STX               -> :class:`JunkBytesError` (reported when the
  next sync arrives, at end of input, or every ``max_junk`` bytes)
* DLE STX inside a frame               -> :class:`TruncatedFrameError`, then the new frame
* DLE followed by neither DLE nor STX  -> :class:`StuffingError`, rescan after the DLE
* Len above 143 words                  -> :class:`FrameLengthError`, rescan after Len
* CRC mismatch                         -> :class:`CrcError` carrying the decoded frame
* input ends inside a frame            -> :class:`TruncatedFrameError` after :meth:`close`

The hidden sync. Inside a frame ``90 90`` is an escaped 0x90 (2.2.4), so a lone
DLE left by damage (a cut frame, a byte changed into 0x90) pairs with the DLE
of the next frame's sync, and ``90 | 90 02`` reads as an escaped 0x90 and a
data byte 0x02. The damaged frame then swallows the next one. So on *every*
error path above, the bytes of the failed frame are scanned again from the
first ``90 02`` after its own sync (and a DLE the failed frame ended on is
scanned again with whatever follows it). The bad frame's bytes before that point are
what the error reports; no byte is reported twice or lost. A later frame is
lost only if the damaged bytes and it together pass the CRC check (one in
65,536 for random damage).

The decisions depend on the bytes alone, never on where the input was cut
into chunks: the decoder waits for a byte it needs (the one after a DLE) instead
of guessing, so any chunking gives the same frames and the same errors.

Memory is bounded: a frame is at most 2 + 2 * (2 + 286 + 2) bytes on the wire,
junk is reported in runs of at most ``max_junk`` bytes, and ``feed`` refuses
to hold more than ``max_pending`` undecoded bytes.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Final, Union

from .codes import DLE, MAX_LEN_WORDS, STX
from .crc import frame_crc
from .errors import (
    CrcError,
    FrameLengthError,
    JunkBytesError,
    LocalProtocolError,
    StuffingError,
    TruncatedFrameError,
)

SYNC: Final = bytes((DLE, STX))
_DLE_BYTE: Final = bytes((DLE,))
_DLE_DLE: Final = bytes((DLE, DLE))
MAX_WIRE_FRAME: Final = 2 + 2 * (2 + 2 * MAX_LEN_WORDS + 2)  # every byte after the sync doubled


class _NeedData:
    __slots__ = ()

    def __repr__(self) -> str:
        return "NEED_DATA"


NEED_DATA: Final = _NeedData()
"""Returned by :meth:`FrameDecoder.next_frame` when no complete frame is buffered."""


@dataclass(frozen=True)
class Frame:
    """One unstuffed frame. ``data`` is the data field (2 * Len bytes)."""

    opcode: int
    data: bytes
    crc: int
    crc_ok: bool = True

    @property
    def length_words(self) -> int:
        return len(self.data) // 2


def encode_frame(opcode: int, data: bytes = b"") -> bytes:
    """``DLE STX OpCode Len Data CRC`` with every 0x90 after the sync doubled."""
    if not 0 <= opcode <= 0xFF:
        raise LocalProtocolError(f"opcode {opcode!r} is not a byte")
    if len(data) % 2:
        raise LocalProtocolError("the data field is made of words: its length must be even")
    words = len(data) // 2
    if words > MAX_LEN_WORDS:
        raise LocalProtocolError(f"{words} data words exceed the maximum of {MAX_LEN_WORDS}")
    crc = frame_crc(opcode, words, data)
    body = bytes((opcode, words)) + data + crc.to_bytes(2, "little")
    return SYNC + body.replace(_DLE_BYTE, _DLE_DLE)


FrameOrNeedData = Union[Frame, _NeedData]


class FrameDecoder:
    """Incremental decoder: :meth:`feed` bytes, then call :meth:`next_frame` until
    it returns :data:`NEED_DATA`. Errors are raised once each; calling again
    continues with the bytes after the damage."""

    def __init__(self, *, max_junk: int = 1024, max_pending: int = 1 << 20) -> None:
        if max_junk < 1:
            raise ValueError("max_junk must be positive")
        self.max_junk = max_junk
        self.max_pending = max_pending
        self._buf = bytearray()   # raw bytes not yet examined
        self._junk = bytearray()  # bytes outside any frame, not yet reported
        self._in_frame = False
        self._body = bytearray()  # unstuffed OpCode, Len, Data, CRC of the current frame
        self._raw = bytearray()   # stuffed bytes of the current frame, for error reports
        self._need = 2            # unstuffed bytes wanted: header first, then the whole frame
        self._eof = False
        self._carry_dle = False   # the last frame ended in "90 90": its last DLE may start a sync

    @property
    def pending(self) -> int:
        """Bytes held that have not yet been returned or reported."""
        return len(self._buf) + len(self._junk) + len(self._raw)

    @property
    def wanted(self) -> int:
        """At least how many more bytes the frame being received needs; 1 outside
        a frame. Stuffing can only add bytes, so this never overstates; a reader
        may wait for that many bytes before it looks again."""
        if not self._in_frame:
            return 1
        return max(1, self._need - len(self._body) - len(self._buf))

    def feed(self, data: bytes) -> None:
        if self._eof:
            raise LocalProtocolError("feed() after close(): the input has ended")
        if len(self._buf) + len(data) > self.max_pending:
            raise LocalProtocolError(
                f"decoder holds {len(self._buf)} undecoded bytes; call next_frame() "
                "until NEED_DATA before feeding more")
        self._buf += data

    def reset(self) -> None:
        """Forget everything buffered (a host flushing stale input before a request)."""
        self.__init__(max_junk=self.max_junk, max_pending=self.max_pending)  # type: ignore[misc]

    def close(self) -> None:
        """End of input. From now on :meth:`next_frame` reports a partial frame and
        unreported junk (each error once) instead of waiting for more bytes."""
        self._eof = True

    def _report_end(self) -> None:
        """At end of input: raise what is left, or return when nothing is."""
        if self._in_frame:
            # A lone DLE in the cut frame may hide a later frame's sync.
            rest = self._give_back_hidden(bytes(self._raw + self._buf), len(self._buf),
                                          open_end=False)
            raise TruncatedFrameError(f"input ended inside a frame ({len(rest)} bytes)", rest)
        leftover = bytes(self._junk + self._buf)
        self._junk.clear()
        self._buf.clear()
        if leftover:
            raise JunkBytesError(f"{len(leftover)} bytes outside any frame", leftover)

    def _start_scan(self) -> None:
        self._in_frame = False
        self._body = bytearray()
        self._raw = bytearray()
        self._need = 2

    def _report_junk(self, count: int) -> None:
        junk = bytes(self._junk[:count])
        del self._junk[:count]
        raise JunkBytesError(f"{len(junk)} bytes outside any frame", junk)

    def next_frame(self) -> FrameOrNeedData:
        while True:
            if not self._in_frame:
                if not self._find_sync():
                    if self._eof:
                        self._report_end()
                    return NEED_DATA
                continue
            buf, body = self._buf, self._body
            i, n = 0, len(buf)
            if not body and n >= 2 and buf[1] <= MAX_LEN_WORDS:
                # Fast path: the whole frame is buffered and holds no DLE, so
                # there is nothing to unstuff (the common case on a healthy link).
                end = 2 + 2 * buf[1] + 2
                if n >= end and buf.find(DLE, 0, end) < 0:
                    body += buf[:end]
                    self._raw += buf[:end]
                    del buf[:end]
                    return self._finish()
            while len(body) < self._need and i < n:
                want = self._need - len(body)
                q = buf.find(DLE, i, i + want)
                if q < 0:
                    take = min(want, n - i)
                    body += buf[i:i + take]
                    i += take
                else:
                    body += buf[i:q]
                    if q + 1 >= n:  # a lone DLE at the end: its meaning is in the next byte
                        i = q
                        break
                    follower = buf[q + 1]
                    if follower == DLE:
                        body.append(DLE)
                        i = q + 2
                    elif follower == STX:
                        # raw ends where the new sync begins: a DLE it ends on is not
                        # followed by STX.
                        raw = self._give_back_hidden(bytes(self._raw + buf[:q]), q,
                                                     open_end=False)
                        raise TruncatedFrameError(
                            f"new DLE STX after {len(raw)} bytes of an unfinished frame", raw)
                    else:
                        # Rescan from the byte after the DLE (so it is not reported twice).
                        raw = self._give_back_hidden(bytes(self._raw + buf[:q + 1]), q + 1,
                                                     open_end=False)
                        raise StuffingError(
                            f"DLE followed by 0x{follower:02X} inside a frame", raw)
                if self._need == 2 and len(body) >= 2:
                    if body[1] > MAX_LEN_WORDS:
                        # "90 02 op 90 | 90 02 ...": a frame cut after its opcode and a
                        # lone DLE reads the next sync's DLE as a stuffed Len of 0x90.
                        raw = self._give_back_hidden(bytes(self._raw + buf[:i]), i,
                                                     open_end=True)
                        raise FrameLengthError(
                            f"Len {body[1]} words exceeds {MAX_LEN_WORDS}", raw)
                    self._need = 2 + 2 * body[1] + 2
            self._raw += buf[:i]
            del buf[:i]
            if len(body) < self._need:
                if self._eof:
                    self._report_end()
                    continue  # bytes given back by _report_end may hold a frame
                return NEED_DATA
            return self._finish()

    def _find_sync(self) -> bool:
        buf = self._buf
        if self._carry_dle:
            if not buf:
                return False
            self._carry_dle = False
            if buf[0] == STX and not self._junk:
                del buf[:1]
                self._start_scan()
                self._in_frame = True
                self._raw += SYNC
                return True
        p = buf.find(SYNC)
        if p < 0:
            # A trailing DLE may be the first half of the next sync: keep it.
            keep = 1 if buf and buf[-1] == DLE else 0
            cut = len(buf) - keep
            self._junk += buf[:cut]
            del buf[:cut]
            if len(self._junk) >= self.max_junk:
                self._report_junk(self.max_junk)
            return False
        self._junk += buf[:p]
        del buf[:p + 2]
        self._start_scan()
        self._in_frame = True
        self._raw += SYNC
        if self._junk:
            self._report_junk(len(self._junk))  # the new frame stays in progress
        return True

    def _give_back_hidden(self, dropped: bytes, consumed: int, *, open_end: bool) -> bytes:
        """The frame in progress failed: drop ``consumed`` bytes of the buffer, and
        give back the bytes of ``dropped`` (its stuffed bytes) from the first place
        a later frame's sync may hide in them (see the module docstring). With
        ``open_end``, what follows ``dropped`` has not been judged, so a DLE it
        ends on is given back too: the next byte decides whether it starts a sync.
        Returns the bytes the error reports."""
        del self._buf[:consumed]
        self._start_scan()
        at = dropped.find(SYNC, 2)  # 2: not the failed frame's own sync
        if at < 0 and open_end and len(dropped) > 2 and dropped[-1] == DLE:
            at = len(dropped) - 1
        if at >= 0:
            self._buf[:0] = dropped[at:]
            dropped = dropped[:at]
        return dropped

    def _finish(self) -> Frame:
        body = bytes(self._body)
        raw = bytes(self._raw)
        self._start_scan()
        opcode, words = body[0], body[1]
        data = body[2:2 + 2 * words]
        received = int.from_bytes(body[-2:], "little")
        expected = frame_crc(opcode, words, data)
        if received != expected:
            frame = Frame(opcode, data, received, crc_ok=False)
            # Since this frame is bad anyway, read any "90 90 02" in it the other
            # way (a lone DLE, then a sync), and a DLE it ends on as a sync's first.
            raw = self._give_back_hidden(raw, 0, open_end=True)
            raise CrcError(
                f"CRC 0x{received:04X} received, 0x{expected:04X} computed", raw, frame)
        # A frame ending in an escaped DLE whose second DLE was really the next
        # sync's (a DLE lost in transit): if STX follows, that is a sync.
        self._carry_dle = raw.endswith(_DLE_DLE)
        return Frame(opcode, data, received)


def decode_frames(data: bytes) -> list[Frame]:
    """All good frames in ``data``; raises the first error met."""
    dec = FrameDecoder()
    dec.feed(data)
    dec.close()
    frames: list[Frame] = []
    while True:
        item = dec.next_frame()
        if isinstance(item, _NeedData):
            return frames
        frames.append(item)
