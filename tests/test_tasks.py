"""tcp_bridge.tasks: a cancellation that wait_for swallows does not keep a task alive."""
from __future__ import annotations

import asyncio
import sys
from typing import List

from tcp_bridge.tasks import cancel_and_wait


async def _poller(turns: List[int], inner: "List[asyncio.Future[int]]") -> None:
    """Loops as the status sampler does: wait_for on one future after another."""
    loop = asyncio.get_running_loop()
    while True:
        fut: "asyncio.Future[int]" = loop.create_future()
        inner.append(fut)
        await asyncio.wait_for(fut, 10)
        turns.append(1)


def _cancel_as_the_result_arrives(task: "asyncio.Task[None]",
                                  inner: "List[asyncio.Future[int]]") -> None:
    # Result and cancellation in one loop iteration: the case of bpo-42130.
    inner[-1].set_result(1)
    task.cancel()


def test_one_cancel_that_meets_a_result_is_swallowed_on_old_pythons() -> None:
    """The premise of the module: documents the CPython behaviour it works around."""
    async def main() -> bool:
        turns: List[int] = []
        inner: "List[asyncio.Future[int]]" = []
        task = asyncio.ensure_future(_poller(turns, inner))
        await asyncio.sleep(0)
        _cancel_as_the_result_arrives(task, inner)
        await asyncio.wait([task], timeout=0.2)
        survived = not task.done()
        task.cancel()
        await asyncio.wait([task], timeout=5)
        return survived

    survived = asyncio.run(main())
    assert survived is (sys.version_info < (3, 12))


def test_cancel_and_wait_ends_a_task_whose_first_cancellation_was_swallowed() -> None:
    async def main() -> None:
        turns: List[int] = []
        inner: "List[asyncio.Future[int]]" = []
        task = asyncio.ensure_future(_poller(turns, inner))
        await asyncio.sleep(0)
        _cancel_as_the_result_arrives(task, inner)
        assert await cancel_and_wait([task], 5.0) == set()
        assert task.cancelled()

    asyncio.run(main())


def test_cancel_and_wait_returns_what_would_not_end_within_the_bound() -> None:
    async def stubborn() -> None:
        while True:
            try:
                await asyncio.sleep(10)
            except asyncio.CancelledError:
                continue  # a task that refuses to end (a bug): reported, not waited for

    async def main() -> None:
        task = asyncio.ensure_future(stubborn())
        await asyncio.sleep(0)
        left = await cancel_and_wait([task], 0.3)
        assert left == {task}
        task.cancel()  # CancelledError is caught: leave it to the loop's end

    loop = asyncio.new_event_loop()
    try:
        loop.run_until_complete(main())
    finally:
        for t in asyncio.all_tasks(loop):
            t.cancel()
        loop.run_until_complete(asyncio.sleep(0))
        loop.close()


def test_done_tasks_and_no_tasks_return_at_once() -> None:
    async def main() -> None:
        assert await cancel_and_wait([], 1.0) == set()
        done = asyncio.ensure_future(asyncio.sleep(0))
        await done
        assert await cancel_and_wait([done], 1.0) == set()

    asyncio.run(main())
