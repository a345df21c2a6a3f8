"""What one estimation tried: every named strategy's attempt, in order, and the time per stage.

The estimator (:mod:`omni_sfm.estimate.pipeline`) reaches its result through a small set of
named strategies (:data:`STRATEGIES`): the paper's method on a window, the same with another
parallel family, the bundle adjustment from another start, a new start after a gap, ... Each
strategy returns an :class:`Attempt` (its solution or none, its cost, and why it stopped), the
caller keeps or rejects it, and the :class:`RunLog` records every attempt with its outcome for
``report.json`` (``attempts``, docs/formats.md). Nothing falls back silently.
"""

from __future__ import annotations

import os
import time
from collections import defaultdict
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, replace
from enum import StrEnum
from typing import Any, Generic, TypeVar

from omni_sfm.forked import SharedCounters
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
    "bootstrap stretch": "the windows and their chain on one stretch of a long sequence "
                         "(EstimationOptions.bootstrap_frames), the next stretch if it fails",
    "short bootstrap": "the whole estimate again from a chain of windows on a short first "
                       "stretch (EstimationOptions.short_bootstrap_frames), the registration "
                       "posing the rest; kept if its poses explain every observation better",
    "reversed start": "the first start's estimate run on the frames in reverse order (its "
                      "chain of windows on the last frames, the registration posing the frames "
                      "before them); kept if its poses explain every observation better",
    "merged starts": "the short bootstrap's main piece with the frames it lacks taken from "
                     "the first start's, moved by the similarity of their poses nearby, then "
                     "adjusted; kept if its poses explain every observation better",
    "paper window": "the paper's method (docs/method.md §4-§5) on one window, with the "
                    "largest parallel family",
    "paper window, unpolished": "the same without the joint rotation polish, where the polished "
                                "rotations jump between frames or disagree with the chain",
    "paper window, another family": "the paper's method on a window with another parallel "
                                    "family, where the first is degenerate there",
    "local adjustment": "the few iterations of bundle adjustment after each chained window",
    "bundle adjustment": "the line bundle adjustment of the chain's frames from the paper's "
                         "solution",
    "bundle adjustment, another start": "the same from one of the paper's alternative "
                                        "starts (translations from another second view); the "
                                        "lowest final cost wins",
    "restart without outliers": "the whole solution again without the tracks the adjustment "
                                "rejected; kept if it estimates as many frames at a cost no "
                                "higher",
    "adjustment from its own result": "the bundle adjustment again from the kept one's poses, "
                                      "every track that is not an outlier triangulated from "
                                      "them (tracks the first start could not triangulate take "
                                      "part); kept if its capped cost on all tracks is lower",
    "lines off the cameras": "the main piece adjusted again where its lines pass through cameras "
                             "that see them (a false minimum): those lines triangulated again "
                             "from its poses, or left out of a first adjustment and triangulated "
                             "from its poses; the lower of the two kept if its capped cost on "
                             "all tracks is lower",
    "registration": "frames beyond the chain posed from the lines already reconstructed, new "
                    "lines triangulated, local adjustments (docs/estimator.md stage 5b)",
    "bundle adjustment after registration": "the adjustment of the chain's and the "
                                            "registered frames together",
    "families held": "an adjustment with the lines of each parallel family held on the "
                     "family's world direction (docs/estimator.md stage 5b); rejected, and the "
                     "directions freed, where those lines fit much worse held",
    "half-turn repair": "short runs of frames turned by a half turn posed again from their "
                        "lines (docs/estimator.md stage 7b)",
    "new start": "the whole estimator again on frames the main solution left (stage 8)",
    "overlap": "a new piece grown by the registration from its lines into the frames of "
               "the pieces beside it, so that the two pose frames in common (stage 8)",
    "join": "a new piece moved into another's world where the poses of the frames both pose, "
            "else their common lines, fix the similarity",
    "bundle adjustment of a piece": "the bundle adjustment of a piece after a join or a "
                                    "half-turn repair",
    "registration again": "up to restart_overlap frames the main piece still lacks at each "
                          "end registered from the lines it knows at the end, after the joins "
                          "and adjustments (stage 8)",
    "rotation only": "rotations alone from the lines, for a camera that turns without moving "
                     "(docs/method.md §13)",
}
"""Every strategy the estimator may try, and what it does (docs/estimator.md)."""


@dataclass(frozen=True)
class Attempt(Generic[T]):
    """One strategy tried on a stretch of frames.

    Attributes:
        strategy: its name, a key of :data:`STRATEGIES`.
        frames: ``(first, last)`` frame it ran on (inclusive, indices of the whole sequence once
            recorded), or None for the whole input.
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

    def record(self, offset: int = 0) -> AttemptRecord:
        """Its entry of the report's ``attempts`` (frames shifted by ``offset``)."""
        return AttemptRecord(
            strategy=self.strategy,
            frames=None if self.frames is None else [self.frames[0] + offset,
                                                     self.frames[1] + offset],
            result=str(self.outcome),
            cost_rms_deg=round(float(self.cost_deg), 6) if self.cost_deg == self.cost_deg
            else None,  # NaN: no solution
            why=self.why or None)


def failed(strategy: str, frames: tuple[int, int] | None, why: str) -> Attempt[Any]:
    """An attempt that gave no solution."""
    return Attempt(strategy, frames, None, why=why, outcome=Outcome.FAILED)


class CountedProgress:
    """What :class:`RunLog` needs of a progress bar (``n``, ``update``, ``set_postfix_str``),
    counting in slot ``k`` of shared counters (:class:`~omni_sfm.forked.SharedCounters`), so
    that a run in a child process shows its progress through the caller's bar; ``on_update``
    (the caller's refresh of that bar) is called only in the process that made this one."""

    def __init__(self, counters: SharedCounters, k: int,
                 on_update: Callable[[], None] | None = None) -> None:
        self.counters, self.k, self.on_update, self.pid = counters, k, on_update, os.getpid()

    @property
    def n(self) -> int:
        return self.counters[self.k]

    def update(self, n: int) -> None:
        self.counters[self.k] = self.counters[self.k] + int(n)
        if self.on_update is not None and os.getpid() == self.pid:
            self.on_update()

    def set_postfix_str(self, s: str = "", refresh: bool = True) -> None:
        """The stage is not shown for such a run."""


class RunLog:
    """Every attempt of one estimation in order (shared by the sub-runs on stretches of frames,
    whose frame indices it shifts to the whole sequence) and the wall time per stage (each run
    its own)."""

    def __init__(self, offset: int = 0, entries: list[AttemptRecord] | None = None,
                 timings: defaultdict[str, float] | None = None,
                 progress: Any | None = None, mirror: int | None = None) -> None:
        self.offset = offset
        self.entries: list[AttemptRecord] = [] if entries is None else entries
        self.timings: defaultdict[str, float] = defaultdict(float) if timings is None \
            else timings
        self.progress = progress
        """A tqdm bar over the whole sequence's frames (shared by the sub-runs), or None."""
        self.mirror = mirror
        """The number of frames of the whole sequence where this run works on its frames in
        reverse order (frame ``k`` of the run is frame ``mirror - 1 - k``), else None."""

    def at(self, offset: int, *, share_timings: bool = False) -> RunLog:
        """A log for a sub-run on frames ``offset..`` (of this run's frames): the same
        attempts and progress bar; its own timings, or these."""
        return RunLog(self.offset + offset, self.entries,
                      self.timings if share_timings else None, self.progress, self.mirror)

    def reversed(self, num_frames: int) -> RunLog:
        """A log for a run on the ``num_frames`` frames of this sequence in reverse order: the
        same attempts, recorded in this sequence's frame indices and marked ``"reversed"``;
        its own timings; the same progress bar, which then counts the frames reached from
        the end."""
        return RunLog(0, self.entries, None, self.progress, num_frames)

    def reached(self, frame: int) -> None:
        """The estimate has got as far as ``frame`` (of this run's frames): the progress bar
        shows the furthest frame reached in the whole sequence."""
        bar = self.progress
        if bar is not None and self.offset + frame + 1 > bar.n:
            bar.update(self.offset + frame + 1 - bar.n)

    def record(self, attempt: Attempt[T], *, to_frames: list[int] | None = None,
               family: int | None = None) -> Attempt[T]:
        """Record ``attempt`` (a join: the piece it was ``to_frames``; a window solved with
        another ``family``) and return it."""
        entry = replace(attempt.record(self.offset), to_frames=to_frames, family=family)
        if self.mirror is not None:
            frames = entry.frames
            if frames is not None:
                a, b = frames
                frames = [self.mirror - 1 - b, self.mirror - 1 - a]
            entry = replace(entry, frames=frames, reversed=True)
        self.entries.append(entry)
        return attempt

    @contextmanager
    def timed(self, stage: str) -> Iterator[None]:
        """Add the wall time of the ``with`` block to ``timings[stage]`` (milliseconds)."""
        t0 = time.perf_counter()
        if self.progress is not None:
            self.progress.set_postfix_str(stage.replace("_", " "), refresh=False)
        try:
            yield
        finally:
            self.timings[stage] += (time.perf_counter() - t0) * 1e3

    def add_times(self, timings: dict[str, float]) -> None:
        for k, v in timings.items():
            self.timings[k] += float(v)
