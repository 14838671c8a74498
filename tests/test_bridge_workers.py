"""Tests of tcp_bridge.workers: one bus thread, jobs in order, the executor's shutdown rules."""
from __future__ import annotations

import asyncio
import threading
import time
from typing import List

import pytest

from tcp_bridge.workers import BusWorker


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
    # The fail-fast probes of a silent bus run here (tcp_bridge.failfast).
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
