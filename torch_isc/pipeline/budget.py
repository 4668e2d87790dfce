"""The wall-clock budget of one batch call (``limits.max_seconds``), seen by the inner loops.

The loop checks the clock between levels; a single level can still run for minutes when a
loop count is large (``anneal_sweeps=1000000``, ``open_rounds=100000``, ``band_iterations``).
Those loops iterate over :func:`rounds` instead of ``range``: once the call's deadline has
passed it stops yielding, so the loop ends with the state it has (every loop of the pipeline
leaves a valid state after any number of rounds: signs stay ±1, magnitudes finite), and the
level finishes with the rest of its (bounded) work. The clock is a host call, not a device
read: checking it every round adds no synchronisation. Without a deadline :func:`rounds` is
``range`` (results are bit-identical).
"""
from __future__ import annotations

import contextlib
import contextvars
import time
from typing import Iterator, Optional

__all__ = ["deadline", "rounds", "stop", "skip", "expired", "cuts"]


class _Budget:
    __slots__ = ("end", "cuts")

    def __init__(self, end: float):
        self.end = end
        self.cuts = 0          # loops this budget has cut short


_CURRENT: contextvars.ContextVar[Optional[_Budget]] = contextvars.ContextVar("torch_isc_budget", default=None)


@contextlib.contextmanager
def deadline(seconds: float, start: Optional[float] = None):
    """Within the block, :func:`rounds` stops ``seconds`` after ``start`` (``perf_counter``;
    now when None). ``seconds <= 0``: no deadline (an enclosing one still holds)."""
    if seconds <= 0:
        yield
        return
    end = (time.perf_counter() if start is None else start) + float(seconds)
    outer = _CURRENT.get()
    if outer is not None:
        end = min(end, outer.end)
    token = _CURRENT.set(_Budget(end))
    try:
        yield
    finally:
        _CURRENT.reset(token)


def expired() -> bool:
    """Whether the current deadline (if any) has passed."""
    b = _CURRENT.get()
    return b is not None and time.perf_counter() > b.end


def cuts() -> int:
    """How many loops the current deadline has cut short (0 without one)."""
    b = _CURRENT.get()
    return 0 if b is None else b.cuts


def rounds(n: int) -> Iterator[int]:
    """``range(n)`` that ends early once the current deadline has passed (the first round always
    runs, so a loop's result is never its untouched start where one round was expected)."""
    n = int(n)
    b = _CURRENT.get()
    if b is None:
        yield from range(n)
        return
    for i in range(n):
        if i and time.perf_counter() > b.end:
            b.cuts += 1
            return
        yield i


def stop(i: int) -> bool:
    """For a ``while`` loop: whether round ``i`` (0-based) should not run because the deadline
    has passed (never the first round); counts the cut like :func:`rounds`."""
    return bool(i) and skip()


def skip() -> bool:
    """For a piece of work done once, not in rounds (a search whose cost grows with the input):
    whether to leave it out because the deadline has passed; counts the cut like :func:`rounds`."""
    b = _CURRENT.get()
    if b is None or time.perf_counter() <= b.end:
        return False
    b.cuts += 1
    return True
