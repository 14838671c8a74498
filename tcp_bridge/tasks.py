"""Ending asyncio tasks for certain, within a bound.

One ``task.cancel()`` does not always end a task on the Python versions we support.
Before 3.12, :func:`asyncio.wait_for` swallows a cancellation that arrives in the
same loop iteration as its inner future's result: it returns that result instead
of raising ``CancelledError`` (CPython bpo-42130 / gh-86296, fixed in 3.12 by the
rewrite of ``wait_for`` over ``asyncio.timeout``). A task that loops (the status
page's sampler, a status stream, a client's connection) then carries on as if it
had never been cancelled, and whoever awaits its end waits for ever. CI caught
exactly that: the status page's ``close()`` hung for 30 s in one run of 2261.

So every shutdown path cancels with :func:`cancel_and_wait`: cancel again until
the task is done or the bound runs out, and tell the caller what is left.
Loops should also check a closing flag of their own, so that a swallowed
cancellation ends them at the next turn even without a second one.
"""
from __future__ import annotations

import asyncio
from typing import Any, Iterable, Set

RETRY: float = 0.25  # seconds between two cancellations, by default


async def cancel_and_wait(tasks: Iterable["asyncio.Future[Any]"], timeout: float, *,
                          retry: float = RETRY) -> Set["asyncio.Future[Any]"]:
    """Cancel ``tasks`` until each is done, for at most ``timeout`` seconds, waiting
    ``retry`` seconds after each cancellation (a task whose clean-up takes time, such
    as a socket's close handshake, needs a ``retry`` longer than that clean-up).

    Returns the tasks still running then (empty when all ended); never raises for
    the tasks' own outcomes, which their owners handle.
    """
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    pending = {t for t in tasks if not t.done()}
    while pending:
        left = deadline - loop.time()
        if left <= 0:
            break
        for task in pending:
            task.cancel()
        _, pending = await asyncio.wait(pending, timeout=min(retry, left))
    return pending
