"""Tests of tcp_bridge.bus.workers: one bus thread, jobs in order, the executor's shutdown rules."""
from __future__ import annotations

import asyncio
import threading
import time
from typing import List

import pytest

from tcp_bridge.bus.workers import BusWorker


def test_jobs_run_in_order_on_the_bus_thread_and_exceptions_arrive() -> None:
    worker = BusWorker("can1")
    seen: List[str] = []

    def job(n: int) -> int:
        seen.append(threading.current_thread().name)
        time.sleep(0.001 * (5 - n))  # later jobs are quicker: order must still hold
        return n

    def broken() -> None:
        raise ValueError("refused")

    async def scenario() -> List[object]:
        futures = [worker.submit(lambda n=n: job(n)) for n in range(5)]
        futures.append(worker.submit(broken))
        return await asyncio.gather(*futures, return_exceptions=True)

    results = asyncio.run(scenario())
    worker.close()
    assert results[:5] == [0, 1, 2, 3, 4]
    assert isinstance(results[5], ValueError)
    assert seen == ["bus-can1"] * 5


def test_a_job_cancelled_before_it_starts_never_runs() -> None:
    worker = BusWorker("can1")
    release = threading.Event()
    ran: List[str] = []

    async def scenario() -> None:
        busy = worker.submit(lambda: release.wait(5))
        queued = worker.submit(lambda: ran.append("queued"))
        queued.cancel()  # e.g. the request timed out
        release.set()
        await busy
        await worker.submit(lambda: None)  # the queue has moved past the cancelled job

    asyncio.run(scenario())
    worker.close()
    assert ran == []


def test_close_finishes_the_job_in_flight_and_cancels_the_queued() -> None:
    worker = BusWorker("can1")
    started = threading.Event()
    release = threading.Event()
    ran: List[str] = []

    def slow() -> str:
        started.set()
        assert release.wait(30), "never released"
        ran.append("slow")
        return "done"

    async def scenario() -> None:
        loop = asyncio.get_running_loop()
        in_flight = worker.submit(slow)
        queued = worker.submit(lambda: ran.append("queued"))
        assert await loop.run_in_executor(None, started.wait, 30)
        closing = loop.run_in_executor(None, worker.close)  # waits for the job in flight
        for _ in range(30_000):  # close() takes the queued job off the queue (<= 30 s)
            if queued.cancelled():
                break
            await asyncio.sleep(0.001)
        assert not closing.done()  # close() is waiting for the job in flight ...
        release.set()
        await closing
        assert await in_flight == "done"  # ... which finished
        with pytest.raises(RuntimeError, match="closed"):
            worker.submit(lambda: None)

    asyncio.run(scenario())
    assert ran == ["slow"]


def test_maintenance_runs_between_jobs_and_while_idle_and_survives_a_bug() -> None:
    # The fail-fast probes of a silent bus run here (tcp_bridge.bus.failfast).
    calls: List[str] = []
    due = threading.Event()
    order: List[str] = []

    def maintenance() -> "float | None":
        calls.append(threading.current_thread().name)
        order.append("maintenance")
        if len(calls) == 3:
            raise RuntimeError("a bug in a probe")
        if len(calls) >= 5:
            due.set()
        return 0.001  # wants to run again soon, queue or not

    worker = BusWorker("can1", maintenance)

    async def scenario() -> None:
        await worker.submit(lambda: order.append("job"))
        await worker.submit(lambda: order.append("job"))

    asyncio.run(scenario())
    assert due.wait(30)  # kept running while idle, after the bug too (retried 1 s later)
    worker.close()
    assert set(calls) == {"bus-can1"}
    first_job = order.index("job")
    assert order[first_job - 1] == "maintenance"  # before each job
    assert order[order.index("job", first_job + 1) - 1] == "maintenance"


# Replies after the next request (defer_results): on a serial link the result of a
# job is handed to the event loop once the next queued job's request is on the wire.


def test_a_result_waits_for_the_next_jobs_request_while_another_job_is_queued() -> None:
    worker = BusWorker("ser1")
    sent = worker.defer_results()
    both_queued = threading.Event()
    first_out = threading.Event()
    seen: List[str] = []

    def second() -> str:
        # Without deferral first's result would already be on its way to the loop.
        seen.append("out before send" if first_out.wait(0.3) else "held")
        sent()  # this job's request is on the wire
        seen.append("out after send" if first_out.wait(5) else "still held")
        return "second"

    async def scenario() -> List[object]:
        first = worker.submit(lambda: both_queued.wait(5) and "first")
        first.add_done_callback(lambda f: first_out.set())
        later = worker.submit(second)
        both_queued.set()
        return list(await asyncio.gather(first, later))

    assert asyncio.run(scenario()) == ["first", "second"]
    worker.close()
    assert seen == ["held", "out after send"]


def test_a_job_that_sends_nothing_hands_over_both_results_even_with_more_queued() -> None:
    worker = BusWorker("ser1")
    worker.defer_results()
    all_queued = threading.Event()
    out = {"first": threading.Event(), "second": threading.Event()}

    def third() -> bool:
        # first was held for second's request; second sent none: both are out now.
        return out["first"].wait(5) and out["second"].wait(5)

    async def scenario() -> List[object]:
        first = worker.submit(lambda: all_queued.wait(5) and "first")
        second = worker.submit(lambda: "second")  # answered without the bus
        last = worker.submit(third)
        for name, future in (("first", first), ("second", second)):
            future.add_done_callback(lambda f, e=out[name]: e.set())
        all_queued.set()
        return list(await asyncio.gather(first, second, last))

    assert asyncio.run(scenario()) == ["first", "second", True]
    worker.close()


def test_with_nothing_queued_a_result_goes_out_at_once_and_the_hook_is_the_workers_own() -> None:
    worker = BusWorker("ser1")
    sent = worker.defer_results()

    async def scenario() -> object:
        sent()  # another thread (Engine.execute_sync) using the link: a no-op
        return await asyncio.wait_for(worker.submit(lambda: "alone"), 5)

    assert asyncio.run(scenario()) == "alone"
    worker.close()


def test_a_held_result_is_not_kept_while_the_next_job_waits_for_a_late_answer() -> None:
    # A result is held until the next job waits on the link. After a request that
    # timed out in silence, EposClient first waits up to late_answer_timeout for the
    # late answer (_swallow_late_answer) before it writes anything: that is waiting
    # too, so the previous job's reply (here a timeout) goes out then, not after it.
    from epos_link.client import EposClient
    from epos_link.errors import EposTimeoutError
    from epos_link.transports.base import Transport

    first_out = threading.Event()
    seen: List[str] = []

    class Silent(Transport):
        url = "silent://"

        def write(self, data: bytes) -> None:
            pass

        def read(self, max_bytes: int, timeout: float) -> bytes:
            # Called by _swallow_late_answer, before the second request is written.
            seen.append("out" if first_out.wait(min(timeout, 1.0)) else "held")
            return b""

        def read_some(self, max_bytes: int, timeout: float, wanted: int = 1) -> bytes:
            time.sleep(min(timeout, 0.05))
            return b""

        def reset_input(self) -> None:
            pass

        def close(self) -> None:
            pass

    client = EposClient(Silent(), timeout=0.05, retries=0, late_answer_timeout=2.0)
    worker = BusWorker("ser1")
    client.on_wait = worker.defer_results()
    both_queued = threading.Event()

    def read() -> bytes:
        both_queued.wait(5)
        return client.read_object(1, 0x6041, 0)

    async def scenario() -> List[object]:
        first = worker.submit(read)
        first.add_done_callback(lambda f: first_out.set())
        second = worker.submit(read)
        both_queued.set()
        return list(await asyncio.gather(first, second, return_exceptions=True))

    outcomes = asyncio.run(scenario())
    worker.close()
    assert all(isinstance(o, EposTimeoutError) for o in outcomes)
    assert seen and seen[0] == "out", seen
