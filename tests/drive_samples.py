"""Sampling simulated drives while they move, and the velocity checks made on the samples.

Shared by the cyclic-move tests (tests/test_bridge_csp.py, test_bridge_csv.py,
test_bridge_ethercat_csp.py): a thread records ``now()`` every few ms; a sample is
a tuple whose first item is the drive's time and whose others the test chooses.
"""
from __future__ import annotations

import threading
import time
from typing import Generic, List, Sequence, Tuple, TypeVar

S = TypeVar("S", bound=Tuple)  # type: ignore[type-arg]
EVERY = 0.004  # seconds between samples


class DriveSampler(Generic[S]):
    """Calls :meth:`now` every :data:`EVERY` s on a thread until :meth:`close`.

    A subclass sets what ``now`` reads *before* calling ``super().__init__()``:
    the thread takes its first sample at once."""

    def __init__(self) -> None:
        self.seen: List[S] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def now(self) -> S:
        raise NotImplementedError

    def _run(self) -> None:
        while not self._stop.is_set():
            self.seen.append(self.now())
            time.sleep(EVERY)

    def close(self) -> List[S]:
        self._stop.set()
        self._thread.join(5)
        return self.seen


def velocities(seen: Sequence[Tuple], which: int = 1,  # type: ignore[type-arg]
               span: float = 0.03) -> List[Tuple[float, float]]:
    """(time, velocity in inc/s) of item ``which`` over windows of at least ``span`` s."""
    out, start = [], seen[0]
    for s in seen[1:]:
        if s[0] - start[0] >= span:
            out.append((s[0], (s[which] - start[which]) / (s[0] - start[0])))
            start = s
    return out


def largest_change(v: List[Tuple[float, float]]) -> float:
    """The largest |dv/dt| between consecutive velocity windows (inc/s^2)."""
    return max(abs(b[1] - a[1]) / (b[0] - a[0]) for a, b in zip(v, v[1:]))
