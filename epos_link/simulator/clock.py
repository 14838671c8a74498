"""A clock for tests and fast simulation: time moves only when told to. Pure."""
from __future__ import annotations

__all__ = ["VirtualClock"]


class VirtualClock:
    """A clock that moves only when told to; pass it as ``Drive(clock=...)``."""

    def __init__(self, start: float = 0.0) -> None:
        self.now = float(start)

    def __call__(self) -> float:
        return self.now

    def advance(self, dt: float) -> float:
        if dt < 0:
            raise ValueError("time cannot run backwards")
        self.now += dt
        return self.now
