"""The replay transport plays a capture as the device and fails loudly on any difference."""
from __future__ import annotations

import threading
import time
from pathlib import Path

import pytest

from epos_link.capture import read_capture
from epos_link.errors import TransportError
from epos_link.transports import open_transport
from epos_link.transports.replay import ReplayMismatchError, ReplayTransport, open_replay

SCRIPT = """\
# epos-link capture v1
0.0 TX 01 02 03 04
0.1 RX AA BB
0.2 RX CC DD EE
0.3 TX 05
0.4 RX FF
"""


def replay() -> ReplayTransport:
    return ReplayTransport(read_capture(SCRIPT), url="replay://test")


def test_writes_may_split_records_any_way_and_reads_follow_records() -> None:
    r = replay()
    assert r.read(10, 0) == b""           # the device waits for the host
    r.write(b"\x01")
    r.write(b"\x02\x03")
    assert r.read(10, 0) == b""           # still not the whole request
    r.write(b"\x04")
    assert r.read(1, 0) == b"\xAA"        # max_bytes splits a record
    assert r.read(10, 0) == b"\xBB"       # a read returns at most one record
    assert r.read(10, 0) == b"\xCC\xDD\xEE"
    r.write(b"\x05")
    assert r.read(10, 0) == b"\xFF"
    assert r.at_end
    r.check_complete()


def test_silence_waits_for_the_timeout() -> None:
    r = replay()
    start = time.monotonic()
    assert r.read(10, 0.05) == b""
    assert 0.04 <= time.monotonic() - start < 2.0  # waited, and returned (40x slack)


def test_a_waiting_read_wakes_up_on_the_hosts_write() -> None:
    r = replay()
    got: list[bytes] = []
    reader = threading.Thread(target=lambda: got.append(r.read(10, 30.0)))
    reader.start()
    time.sleep(0.02)
    r.write(b"\x01\x02\x03\x04")
    reader.join(30)
    assert got == [b"\xAA\xBB"]


@pytest.mark.parametrize("writes, message", [
    ([b"\x01\x02\x09"], "record 1 expects the host to send 01 02 03 04, host sent 01 02 09"),
    ([b"\x01\x02\x03\x04\x05"], "while record 2 has the device send AA BB"),
])
def test_mismatches_are_loud(writes: list[bytes], message: str) -> None:
    r = replay()
    with pytest.raises(ReplayMismatchError) as info:
        for data in writes:
            r.write(data)
    assert message in str(info.value)
    assert isinstance(info.value, AssertionError)


def test_writing_after_the_end() -> None:
    r = ReplayTransport(read_capture("0 TX 01\n"))
    r.write(b"\x01")
    with pytest.raises(ReplayMismatchError, match="after the end of the recording"):
        r.write(b"\x02")


def test_reset_input_discards_readable_records_only() -> None:
    r = replay()
    r.reset_input()                      # nothing readable yet: the TX stays expected
    r.write(b"\x01\x02\x03\x04")
    r.read(1, 0)
    r.reset_input()                      # the rest of AA BB and CC DD EE are stale
    r.write(b"\x05")
    assert r.read(10, 0) == b"\xFF"


def test_check_complete_names_what_is_left() -> None:
    r = replay()
    r.write(b"\x01\x02")
    with pytest.raises(ReplayMismatchError, match="record 1 of 5 not played: TX 03 04"):
        r.check_complete()
    assert [rec.data for rec in r.remaining()][:2] == [b"\x01\x02\x03\x04", b"\xAA\xBB"]


def test_close_and_reopen() -> None:
    r = replay()
    r.close()
    with pytest.raises(TransportError):
        r.write(b"\x01")
    with pytest.raises(TransportError):
        r.read(1, 0)
    r.reopen()
    r.write(b"\x01\x02\x03\x04")


def test_open_by_url(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    (tmp_path / "c.txt").write_text(SCRIPT)
    absolute = open_transport(f"replay://{tmp_path / 'c.txt'}", baudrate=9600)
    assert isinstance(absolute, ReplayTransport)
    monkeypatch.chdir(tmp_path)
    relative = open_replay("replay://c.txt")
    relative.write(b"\x01\x02\x03\x04")
    assert relative.read(10, 0) == b"\xAA\xBB"
    with pytest.raises(TransportError, match="cannot open"):
        open_replay("replay://missing.txt")
    with pytest.raises(TransportError, match="needs a capture file"):
        open_replay("replay://")
