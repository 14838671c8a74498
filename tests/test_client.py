"""EposClient against scripted TX/RX conversations (fixtures/client_*.txt, played by
the replay transport, which fails loudly when the client sends other bytes)."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Iterator

import pytest

from epos_link.capture import Capture, read_capture
from epos_link.client import EposClient, NodeInfo
from epos_link.codes import NmtCommand
from epos_link.errors import (
    CrcError,
    DeviceError,
    EposTimeoutError,
    GatewayNotSupportedError,
    LocalProtocolError,
    TransportError,
)
from epos_link.segmented import ToggleBitError
from epos_link.transports.base import Transport
from epos_link.transports.replay import ReplayMismatchError, ReplayTransport

FIXTURES = Path(__file__).parent.parent / "fixtures"
NAME = b"EPOS4 Compact 50/8 CAN"
FAST = 0.05  # a silent device costs this much per attempt


def load(name: str) -> Capture:
    with open(FIXTURES / name, encoding="utf-8") as fh:
        return read_capture(fh)


@pytest.fixture
def play() -> Iterator[Any]:
    """play(fixture, **client_options) -> (client, replay); the whole script must be played."""
    opened: list[ReplayTransport] = []

    def make(name: str, **options: Any) -> tuple[EposClient, ReplayTransport]:
        replay = ReplayTransport(load(name), url=f"replay://{name}")
        opened.append(replay)
        options.setdefault("timeout", FAST)
        return EposClient(replay, **options), replay

    yield make
    for replay in opened:
        replay.check_complete()


def test_stuffed_values_both_ways(play: Any) -> None:
    client, _ = play("client_stuffed.txt")
    assert client.read_object(1, 0x6064, 0) == b"\x90\x90\x90\x90"
    client.write_object(1, 0x607A, 0, b"\x90\x90\x90")  # padded with one zero byte


def test_segmented_read_first_chunk_in_initiate_answer(play: Any) -> None:
    client, _ = play("client_segmented_read_inline.txt")
    assert client.upload(1, 0x1008, 0) == NAME


def test_segmented_read_initiate_answer_without_data(play: Any) -> None:
    client, _ = play("client_segmented_read_separate.txt")
    assert client.upload(0, 0x1008, 0, size=100) == NAME  # size > 4: segmented, whole object


def test_segmented_read_restarts_from_the_beginning(play: Any) -> None:
    client, _ = play("client_segmented_read_restart.txt")
    assert client.upload(1, 0x1008, 0) == NAME


def test_segmented_read_without_retries_reports_the_toggle_error() -> None:
    replay = ReplayTransport(load("client_segmented_read_restart.txt"))
    with pytest.raises(ToggleBitError):
        EposClient(replay, retries=0).upload(1, 0x1008, 0)


def test_segmented_write(play: Any) -> None:
    client, _ = play("client_segmented_write.txt", segment_size=4)
    client.download(0, 0x2100, 1, b"123456789")


def test_error_answers_are_typed_and_not_retried(play: Any) -> None:
    client, _ = play("client_error_answer.txt")
    with pytest.raises(DeviceError) as info:
        client.read_object(1, 0x1234, 0)
    assert info.value.code == 0x06020000
    assert info.value.name == "Object does not exist error"
    assert "0x06020000" in str(info.value) and "node 1 0x1234/0x00" in str(info.value)
    with pytest.raises(DeviceError) as info:
        client.download(1, 0x1000, 0, b"\x01")
    assert info.value.code == 0x06010002


def test_corrupted_reply_then_retry(play: Any) -> None:
    client, _ = play("client_crc_retry.txt")
    assert client.read_object(1, 0x6064, 0) == b"\xE8\x03\x00\x00"


def test_corrupted_reply_without_retry_is_a_crc_error() -> None:
    replay = ReplayTransport(load("client_crc_retry.txt"))
    with pytest.raises(CrcError):
        EposClient(replay, retries=0).read_object(1, 0x6064, 0)


def test_junk_before_replies(play: Any) -> None:
    client, _ = play("client_junk.txt")
    values = [int.from_bytes(client.read_object(1, 0x6064, 0), "little") for _ in range(3)]
    assert values == [1000, 1001, 1002]


def test_silent_device_times_out_after_one_retry(play: Any) -> None:
    client, _ = play("client_silent.txt")
    with pytest.raises(EposTimeoutError) as info:
        client.read_object(1, 0x6064, 0)
    assert isinstance(info.value, TimeoutError)
    assert "ReadObject node 1 0x6064/0x00" in str(info.value)


def test_retries_are_configurable_and_replay_fails_loudly() -> None:
    # Two retries send the request three times; the recording has it twice.
    replay = ReplayTransport(load("client_silent.txt"))
    with pytest.raises(ReplayMismatchError, match="after the end of the recording"):
        EposClient(replay, timeout=FAST, retries=2).read_object(1, 0x6064, 0)


def test_other_bytes_than_recorded_are_a_mismatch_not_a_retry() -> None:
    replay = ReplayTransport(load("client_stuffed.txt"))
    with pytest.raises(ReplayMismatchError, match="record 1 expects"):
        EposClient(replay).read_object(2, 0x6064, 0)


def test_stale_input_is_discarded(play: Any) -> None:
    client, _ = play("client_stale.txt")
    assert client.upload(1, 0x6064, 0, size=4) == b"\x22" * 4


def test_expedited_upload_truncates_to_size(play: Any) -> None:
    client, _ = play("client_stale.txt")
    assert client.upload(1, 0x6064, 0, size=2) == b"\x22\x22"


def test_nmt(play: Any) -> None:
    client, _ = play("client_nmt.txt")
    client.nmt(2, "start")
    client.nmt(0, NmtCommand.ENTER_PRE_OPERATIONAL)


def test_nmt_unknown_command() -> None:
    client = EposClient(ReplayTransport(Capture()))
    with pytest.raises(LocalProtocolError):
        client.nmt(1, "jump")
    with pytest.raises(LocalProtocolError):
        client.nmt(1, 0x55)


def test_scan(play: Any) -> None:
    client, _ = play("client_scan.txt")
    assert client.scan([1, 2, 3], timeout=FAST) == [
        NodeInfo(1, 0x00020192, "EPOS4", 0xFB, 0x61500000, 0x01700000, 0x12345678)]


class Recorder(Transport):
    """Records writes and never answers."""

    url = "recorder://"

    def __init__(self) -> None:
        self.written: list[bytes] = []

    def write(self, data: bytes) -> None:
        self.written.append(bytes(data))

    def read(self, max_bytes: int, timeout: float) -> bytes:
        return b""

    def close(self) -> None:
        pass


def test_segmented_write_to_a_remote_node_is_refused_before_sending() -> None:
    link = Recorder()
    client = EposClient(link, timeout=FAST)
    with pytest.raises(GatewayNotSupportedError, match="2.1.2.2"):
        client.download(2, 0x2100, 1, b"123456789")
    assert link.written == []
    assert isinstance(GatewayNotSupportedError("x"), LocalProtocolError)


def test_segmented_write_to_the_gateways_own_id_is_sent() -> None:
    link = Recorder()
    client = EposClient(link, gateway_node_id=2, timeout=FAST, retries=0)
    with pytest.raises(EposTimeoutError):
        client.download(2, 0x2100, 1, b"123456789")
    assert link.written[0][2] == 0x69 and link.written[0][4] == 2  # InitiateSegmentedWrite, node 2


def test_write_object_refuses_more_than_four_bytes() -> None:
    client = EposClient(Recorder())
    with pytest.raises(LocalProtocolError):
        client.write_object(1, 0x2000, 0, b"12345")
    with pytest.raises(LocalProtocolError):
        client.read_object(128, 0x1000, 0)


class Flaky(Transport):
    """A replay whose first write fails like an unplugged cable; counts reopens."""

    def __init__(self, inner: ReplayTransport, failures: int = 1) -> None:
        self.inner = inner
        self.url = inner.url
        self.failures = failures
        self.reopened = 0
        self.broken = False

    def write(self, data: bytes) -> None:
        if self.broken:
            raise TransportError("still unplugged")
        if self.failures:
            self.failures -= 1
            self.broken = True
            raise TransportError("unplugged")
        self.inner.write(data)

    def read(self, max_bytes: int, timeout: float) -> bytes:
        return self.inner.read(max_bytes, timeout)

    def reset_input(self) -> None:
        if not self.broken:
            self.inner.reset_input()

    def reopen(self) -> None:
        self.reopened += 1
        self.broken = False

    def close(self) -> None:
        self.inner.close()


def test_transport_error_reopens_on_the_next_attempt() -> None:
    replay = ReplayTransport(load("client_stale.txt"))
    link = Flaky(replay)
    assert EposClient(link).read_object(1, 0x6064, 0) == b"\x22" * 4
    assert link.reopened == 1
    replay.check_complete()


def test_transport_error_after_the_last_retry_is_raised_and_the_next_call_reopens() -> None:
    replay = ReplayTransport(load("client_stale.txt"))
    link = Flaky(replay, failures=1)
    client = EposClient(link, retries=0)
    with pytest.raises(TransportError):
        client.read_object(1, 0x6064, 0)
    assert link.reopened == 0
    assert client.read_object(1, 0x6064, 0) == b"\x22" * 4
    assert link.reopened == 1


def test_context_manager_closes_the_transport() -> None:
    replay = ReplayTransport(Capture())
    with EposClient(replay) as client:
        assert client.transport is replay
    with pytest.raises(TransportError):
        replay.write(b"x")


def test_open_replay_url_with_trace(tmp_path: Path) -> None:
    trace = tmp_path / "trace.txt"
    with EposClient.open(f"replay://{FIXTURES / 'client_crc_retry.txt'}", trace=str(trace),
                         baudrate=9600) as client:
        assert client.read_object(1, 0x6064, 0) == b"\xE8\x03\x00\x00"
    recorded = read_capture(trace.read_text())
    original = load("client_crc_retry.txt")
    assert [(r.direction, r.data) for r in recorded.records] == \
        [(r.direction, r.data) for r in original.records]
    assert any(c.startswith("source: epos-link trace of replay://") for c in recorded.comments)


def test_on_wait_is_called_once_per_request_after_its_frame_is_written(play: Any) -> None:
    # tcp_bridge hands a finished reply to its event loop from this hook, while
    # the wire carries the next request: it must come after the write, never before.
    client, replay = play("client_segmented_read_inline.txt")
    calls: list[int] = []
    write = replay.write

    def counting_write(data: bytes) -> None:
        calls.append(-1)  # a write
        write(data)

    replay.write = counting_write  # type: ignore[method-assign]
    client.on_wait = lambda: calls.append(+1)
    assert client.upload(1, 0x1008, 0) == NAME
    assert calls and calls == [-1, +1] * (len(calls) // 2)
