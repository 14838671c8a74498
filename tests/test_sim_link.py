"""``--baud`` pacing of the simulated link (issue 10, item 9), on an injected clock.

A UART at B baud sends one 8N1 byte (10 bits, guide 2.2.6) every 10/B
seconds. The link must hand over answer byte i when its stop bit is past,
``start + (i + 1) * 10 / B``, not in bursts followed by a pause. No wall
clock is involved: the clock is a counter that the fake sleep advances.
"""
from __future__ import annotations

from typing import Optional

import pytest

from epos_link.simulator.link import LinkOptions, LinkServer

ANSWER = bytes(range(20))


class FakeTime:
    def __init__(self, oversleep: float = 0.0) -> None:
        self.now = 100.0
        self.oversleep = oversleep  # a late wake-up, added to every sleep
        self.sleeps: list[float] = []

    def clock(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.sleeps.append(seconds)
        self.now += seconds + self.oversleep


class EchoDevice:
    def __init__(self) -> None:
        self.requests: list[bytes] = []

    def receive(self, data: bytes) -> list[bytes]:
        self.requests.append(data)
        return [ANSWER]

    def reset(self) -> None:
        pass


def serve_one(baud: Optional[int], fake: FakeTime, request: bytes = b"0123456789") -> list[tuple[float, bytes]]:
    """One request through LinkServer; the writes with their (fake) times."""
    writes: list[tuple[float, bytes]] = []
    feed = [request]
    server = LinkServer(EchoDevice(), LinkOptions(baud=baud), clock=fake.clock, sleep=fake.sleep,
                        spin=0.0)  # a fake clock that only sleeps advance: no waiting on it

    def read(timeout: float) -> Optional[bytes]:
        return feed.pop() if feed else None  # then the host closes

    server.serve_stream(read, lambda data: writes.append((fake.now, bytes(data))))
    return writes


@pytest.mark.parametrize("baud", [9600, 115200, 1_000_000])
def test_each_byte_at_wire_speed(baud: int) -> None:
    fake = FakeTime()
    writes = serve_one(baud, fake)
    per_byte = 10 / baud
    request_done = 100.0 + 10 * per_byte  # the 10 request bytes arrive first
    assert [data for _, data in writes] == [bytes([b]) for b in ANSWER]  # one byte per write
    for i, (t, _) in enumerate(writes):
        assert t == pytest.approx(request_done + (i + 1) * per_byte, rel=1e-9)


def test_late_wake_ups_are_caught_up_not_accumulated() -> None:
    baud = 115200
    per_byte = 10 / baud
    fake = FakeTime(oversleep=2.5 * per_byte)  # every wake-up 2.5 bytes late
    writes = serve_one(baud, fake)
    assert b"".join(data for _, data in writes) == ANSWER
    start = 100.0 + 10 * per_byte  # the answer's schedule starts when the request is in
    sent = 0
    for t, data in writes:
        sent += len(data)
        assert t >= start + sent * per_byte - 1e-12  # never a byte before its wire time
    # the whole answer takes its wire time plus one late wake-up, not 20 of them
    assert writes[-1][0] - start <= len(ANSWER) * per_byte + 2.5 * per_byte + 1e-12
    assert len(writes) < len(ANSWER)  # some writes carried several due bytes


def test_without_baud_the_answer_goes_at_once() -> None:
    fake = FakeTime()
    writes = serve_one(None, fake)
    assert writes == [(100.0, ANSWER)] and fake.sleeps == []


def test_answers_follow_each_other_on_one_wire() -> None:
    """Two frames answered from one read: the second starts when the first has left."""

    class TwoAnswers(EchoDevice):
        def receive(self, data: bytes) -> list[bytes]:
            return [b"ab", b"cd"]

    fake = FakeTime()
    writes: list[tuple[float, bytes]] = []
    feed = [b"12345"]
    server = LinkServer(TwoAnswers(), LinkOptions(baud=10_000), clock=fake.clock, sleep=fake.sleep, spin=0.0)
    server.serve_stream(lambda timeout: feed.pop() if feed else None,
                        lambda data: writes.append((fake.now, bytes(data))))
    per_byte = 10 / 10_000
    start = 100.0 + 5 * per_byte
    assert writes == [(pytest.approx(start + k * per_byte), bytes([c]))
                      for k, c in enumerate(b"abcd", start=1)]


@pytest.mark.skipif(not __import__("sys").platform.startswith("linux"),
                    reason="timer slack is a Linux setting (prctl PR_SET_TIMERSLACK)")
def test_a_paced_pty_link_serves_with_a_1_us_timer_slack_and_a_short_spin() -> None:
    # A sleep wakes up to 50 us late by default; the link thread asks for 1 us so
    # that it can time an answer's last byte with a short spin (module docstring).
    import os
    import time

    from epos_link.simulator.core import Epos4Simulator
    from epos_link.simulator.link import PRECISE_SPIN, PtyLink

    sim = Epos4Simulator(1, [])
    link = PtyLink(sim, LinkOptions(baud=115200)).start()
    try:
        deadline = time.monotonic() + 10
        while link.server.spin != PRECISE_SPIN and time.monotonic() < deadline:
            time.sleep(0.01)
        assert link.server.spin == PRECISE_SPIN
        slack = f"/proc/{os.getpid()}/task/{link._thread.native_id}/timerslack_ns"
        if os.path.exists(slack):
            with open(slack, encoding="ascii") as fh:
                assert int(fh.read()) == 1000
    finally:
        link.close()
        sim.close()


class TimedReads:
    """Host reads on the fake clock: each step is (seconds of silence, bytes)."""

    def __init__(self, fake: FakeTime, steps: list[tuple[float, bytes]]) -> None:
        self.fake, self.steps = fake, steps

    def __call__(self, timeout: float) -> Optional[bytes]:
        if not self.steps:
            return None
        wait, data = self.steps[0]
        if wait > timeout:  # nothing within this read: the time passes, empty read
            self.steps[0] = (wait - timeout, data)
            self.fake.now += timeout
            return b""
        self.steps.pop(0)
        self.fake.now += wait
        return data


def resets_while_serving(frame_timeout_ms: Optional[int], silence: float, *,
                         usb: bool = False) -> int:
    """Serve a simulated EPOS4 a partial frame, then ``silence`` s; count frame-timeout resets."""
    from epos_link.simulator.core import Epos4Simulator
    from epos_link.simulator.link import RS232_FRAME_TIMEOUT, USB_FRAME_TIMEOUT

    index = USB_FRAME_TIMEOUT if usb else RS232_FRAME_TIMEOUT
    fake = FakeTime()
    with Epos4Simulator(1, []) as sim:
        if frame_timeout_ms is not None:
            sim.own.store.write_value(index, 0, frame_timeout_ms)
        resets: list[float] = []
        reset = sim.reset

        def counting_reset() -> None:
            resets.append(fake.now)
            reset()
        sim.reset = counting_reset  # type: ignore[method-assign]
        server = LinkServer(sim, LinkOptions(), clock=fake.clock, sleep=fake.sleep, spin=0.0,
                            frame_timeout_object=index)
        server.serve_stream(TimedReads(fake, [(0.0, b"\x90\x02\x60"), (silence, b"")]),
                            lambda data: None)
        return len(resets) - 1  # the first reset is the link's start


def test_the_frame_timeout_is_2005h_default_500_ms() -> None:
    # Guide 2.2.7, Table 2-4: RS232 Frame Timeout 2005h, default 500 ms.
    assert resets_while_serving(None, 0.4) == 0
    assert resets_while_serving(None, 0.6) == 1


def test_a_written_2005h_sets_the_frame_timeout() -> None:
    # "the timeout may be changed by writing to the Object Dictionary" (guide 2.2.7).
    assert resets_while_serving(100, 0.15) == 1  # 100 ms: the partial frame is gone
    assert resets_while_serving(1000, 0.7) == 0  # 1 s: still waiting for its rest


def test_the_usb_link_uses_2006h() -> None:
    assert resets_while_serving(100, 0.15, usb=True) == 1
