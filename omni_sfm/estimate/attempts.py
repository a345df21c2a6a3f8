"""What one estimation tried: every named strategy's attempt, in order, and the time per stage.

The estimator (:mod:`omni_sfm.estimate.pipeline`) reaches its result through a small set of
named strategies (:data:`STRATEGIES`): the paper's method on its window, the same with another
parallel family, the bundle adjustment from another start, the rotation-only fit. Each
strategy returns an :class:`Attempt` (its solution or none, its cost, and why it stopped), the
caller keeps or rejects it, and the :class:`RunLog` records every attempt with its outcome for
``report.json`` (``attempts``, docs/formats.md). Nothing falls back silently.
"""

from __future__ import annotations

import time
from collections import defaultdict
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, replace
from enum import StrEnum
from typing import Any, Generic, TypeVar

from omni_sfm.reports import AttemptRecord

T = TypeVar("T")


class Outcome(StrEnum):
    """What became of an attempt."""

    KEPT = "kept"
    """Its solution is (part of) the result."""
    REJECTED = "rejected"
    """It gave a solution, and another one was better (``why`` says by what)."""
    FAILED = "failed"
    """It gave no solution (``why`` says why it stopped)."""
    SKIPPED = "skipped"
    """Not run: it could not change the result (``why`` says why)."""


STRATEGIES: dict[str, str] = {
    "paper window": "the paper's method (docs/method.md §4-§5) on the window that covers the "
                    "sequence, with the largest parallel family",
    "paper window, unpolished": "the same without the joint rotation polish, where the polished "
                                "rotations jump between frames",
    "paper window, another family": "the paper's method with another parallel family, where "
                                    "the first is degenerate for the motion",
    "bundle adjustment": "the line bundle adjustment from the paper's solution",
    "bundle adjustment, another start": "the same from one of the paper's alternative "
                                        "starts (translations from another second view); the "
                                        "lowest final cost wins",
    "rotation only": "rotations alone from the lines, for a camera that turns without moving "
                     "(docs/method.md §13)",
}
"""Every strategy the estimator may try, and what it does (docs/estimator.md)."""


@dataclass(frozen=True)
class Attempt(Generic[T]):
    """One strategy tried on a stretch of frames.

    Attributes:
        strategy: its name, a key of :data:`STRATEGIES`.
        frames: ``(first, last)`` frame it ran on (inclusive), or None for the whole input.
        solution: what it produced, None when it failed.
        cost_deg: the RMS angle between observed and predicted line normals at its solution
            (the cost that decides between attempts), NaN when it has none.
        why: why it stopped, or why its solution was kept or rejected.
        outcome: see :class:`Outcome`.
    """

    strategy: str
    frames: tuple[int, int] | None
    solution: T | None
    cost_deg: float = float("nan")
    why: str = ""
    outcome: Outcome = Outcome.KEPT

    def __post_init__(self) -> None:
        if self.strategy not in STRATEGIES:
            raise ValueError(f"unknown strategy {self.strategy!r}")

    @property
    def ok(self) -> bool:
        """Whether it produced a solution."""
        return self.solution is not None

    def judged(self, outcome: Outcome, why: str | None = None) -> Attempt[T]:
        """The same attempt with the caller's verdict."""
        return replace(self, outcome=outcome, why=self.why if why is None else why)

    def record(self) -> AttemptRecord:
        """Its entry of the report's ``attempts``."""
        return AttemptRecord(
            strategy=self.strategy,
            frames=None if self.frames is None else [self.frames[0], self.frames[1]],
            result=str(self.outcome),
            cost_rms_deg=round(float(self.cost_deg), 6) if self.cost_deg == self.cost_deg
            else None,  # NaN: no solution
            why=self.why or None)


def failed(strategy: str, frames: tuple[int, int] | None, why: str) -> Attempt[Any]:
    """An attempt that gave no solution."""
    return Attempt(strategy, frames, None, why=why, outcome=Outcome.FAILED)


class RunLog:
    """Every attempt of one estimation in order and the wall time per stage."""

    def __init__(self) -> None:
        self.entries: list[AttemptRecord] = []
        self.timings: defaultdict[str, float] = defaultdict(float)

    def record(self, attempt: Attempt[T], *, family: int | None = None) -> Attempt[T]:
        """Record ``attempt`` (solved with another parallel ``family``: its number) and return
        it."""
        self.entries.append(replace(attempt.record(), family=family))
        return attempt

    @contextmanager
    def timed(self, stage: str) -> Iterator[None]:
        """Add the wall time of the ``with`` block to ``timings[stage]`` (milliseconds)."""
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.timings[stage] += (time.perf_counter() - t0) * 1e3

    def add_times(self, timings: dict[str, float]) -> None:
        for k, v in timings.items():
            self.timings[k] += float(v)
