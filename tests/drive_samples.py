"""Sampling simulated drives while they move, and the velocity checks made on the samples.

Shared by the cyclic-move tests (tests/test_bridge_csp.py, test_bridge_csv.py,
test_bridge_ethercat_csp.py): a thread records ``now()`` every few ms; a sample is
a tuple whose first item is the drive's time and whose others the test chooses.
"""
from __future__ import annotations

import threading
import time
from typing import Any, Dict, Generic, List, Sequence, Tuple, TypeVar

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


class SentSetpoints:
    """Every set-point a :class:`~tcp_bridge.motion.cyclic.CyclicSender` sends, with the
    time its profile was sampled at: ``positions`` and ``velocities`` are lists of
    ``(time, {node: value})``.

    The sender samples its profile at ``now = clock()`` and sends the result at once
    (``_cycle``), so this records the clock's last reading on the sender's thread with
    each send. The stream then reads as the bridge computed it, whatever the machine
    did meanwhile: a cycle that a loaded machine delays is sent late with the value
    of its late moment, which is right (the module's timing rule), but the drive
    holds the previous set-point until it arrives, so samples of the drive show a
    step that no set-point had (issue 32: the stop-mid-move tests failed 7 of 36 runs
    at moderate load). "Never a step" is a rule of the stream: it is checked here,
    exactly; where the drive ends up is still checked on the drive."""

    def __init__(self, sender: Any) -> None:
        self.positions: List[Tuple[float, Dict[int, int]]] = []
        self.velocities: List[Tuple[float, Dict[int, int]]] = []
        self._sampled = threading.local()
        clock = sender.clock
        transport = sender.transport
        write_targets, write_velocities = transport.write_targets, transport.write_velocities

        def recording_clock() -> float:
            self._sampled.at = now = clock()
            return now

        def targets(values: Dict[int, int]) -> None:
            write_targets(values)
            self.positions.append((self._sampled.at, dict(values)))

        def velocities(values: Dict[int, int]) -> None:
            write_velocities(values)
            self.velocities.append((self._sampled.at, dict(values)))

        sender.clock = recording_clock
        transport.write_targets = targets
        transport.write_velocities = velocities

    @staticmethod
    def series(sent: List[Tuple[float, Dict[int, int]]], node: int,
               since: float = float("-inf")) -> List[Tuple[float, int]]:
        """``(time, value)`` of ``node`` from ``since`` on."""
        return [(t, values[node]) for t, values in sent if node in values and t >= since]
