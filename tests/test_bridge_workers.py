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
    ran: List[str] = []

    def slow() -> str:
        started.set()
        time.sleep(0.2)
        ran.append("slow")
        return "done"

    async def scenario() -> None:
        in_flight = worker.submit(slow)
        queued = worker.submit(lambda: ran.append("queued"))
        await asyncio.get_running_loop().run_in_executor(None, started.wait, 5)
        await asyncio.get_running_loop().run_in_executor(None, worker.close)
        assert await in_flight == "done"
        with pytest.raises(asyncio.CancelledError):
            await queued
        with pytest.raises(RuntimeError, match="closed"):
            worker.submit(lambda: None)

    asyncio.run(scenario())
    assert ran == ["slow"]
