"""A computation started now in a forked child process, its result taken later.

:class:`Deferred` runs a function of no arguments either in a child process forked at once
(``fork=True`` where the platform forks: the child shares the caller's memory, so nothing is
copied in; only the result comes back, pickled) or, otherwise, in the calling process when its
result is first asked for. The function is the same in both cases, so the result is the same
to the bit: only the wall time differs. An exception raised by the function is raised again
by :meth:`Deferred.result` in the caller. A child not waited for is stopped by
:meth:`Deferred.cancel` (and, being a daemon, when the caller exits).
"""

from __future__ import annotations

import multiprocessing as mp
import pickle
import traceback
from collections.abc import Callable, Sequence
from functools import partial
from multiprocessing.connection import Connection
from typing import Any, Generic, TypeVar

T = TypeVar("T")


def can_fork() -> bool:
    """Whether this platform starts child processes by forking (Linux; not Windows)."""
    return "fork" in mp.get_all_start_methods()


def _child(fn: Callable[[], Any], conn: Connection) -> None:
    try:
        out: tuple[str, Any] = ("ok", fn())
    except BaseException as exc:  # noqa: BLE001 - every exception goes back to the caller
        out = ("error", exc)
    try:
        conn.send(out)
    except (pickle.PicklingError, TypeError, AttributeError) as exc:
        what = "".join(traceback.format_exception(out[1])) if out[0] == "error" else \
            f"{type(out[1]).__name__}"
        conn.send(("error", RuntimeError(f"a worker's result could not be sent back ({exc}): "
                                         f"{what}")))
    finally:
        conn.close()


class Deferred(Generic[T]):
    """``fn()``, run in a forked child from now on (``fork`` and :func:`can_fork`; or from a
    later :meth:`start`), else in this process when :meth:`result` is first called (module
    docstring)."""

    def __init__(self, fn: Callable[[], T], *, fork: bool = False) -> None:
        self._fn = fn
        self._proc: Any = None
        self._conn: Connection | None = None
        self._value: tuple[str, Any] | None = None
        if fork:
            self.start()

    def start(self) -> None:
        """Run ``fn`` in a forked child from now on, where the platform forks and it has not
        started yet (else nothing)."""
        if self._proc is not None or self._value is not None or not can_fork():
            return
        ctx = mp.get_context("fork")
        recv, send = ctx.Pipe(duplex=False)
        self._proc = ctx.Process(target=_child, args=(self._fn, send), daemon=True)
        self._proc.start()
        send.close()
        self._conn = recv

    @property
    def forked(self) -> bool:
        """Whether ``fn`` runs in a child process."""
        return self._proc is not None

    def result(self, while_waiting: Callable[[], None] | None = None,
               interval: float = 0.5) -> T:
        """``fn()``'s value (waiting for the child, calling ``while_waiting`` every
        ``interval`` seconds meanwhile), or its exception raised here."""
        if self._value is None:
            if self._proc is None:
                self._value = ("ok", self._fn())
            else:
                assert self._conn is not None
                try:
                    if while_waiting is not None:
                        while not self._conn.poll(interval):
                            while_waiting()
                    self._value = self._conn.recv()
                except EOFError:
                    self._proc.join()
                    raise RuntimeError(f"a worker process ended without a result (exit code "
                                       f"{self._proc.exitcode})") from None
                finally:
                    self._conn.close()
                self._proc.join()
                self._proc = None
        status, value = self._value
        if status == "error":
            assert isinstance(value, BaseException)
            raise value
        out: T = value
        return out

    def cancel(self) -> None:
        """Stop the child if it still runs (its result is then never asked for)."""
        if self._proc is not None:
            self._proc.terminate()
            self._proc.join()
            self._proc = None
            if self._conn is not None:
                self._conn.close()


def _run_group(fns: Sequence[Callable[[], T]], idx: range) -> list[T]:
    return [fns[i]() for i in idx]


def run_all(fns: Sequence[Callable[[], T]], workers: int) -> list[T]:
    """``[fn() for fn in fns]``, up to ``workers`` of them at once: the calls are dealt to
    ``workers`` groups in turn (call ``k`` to group ``k mod workers``), each group but the first
    run in a forked child (:class:`Deferred`), the first in this process. Every call is the
    same function wherever it runs, so the results are the same to the bit whatever
    ``workers``; an exception is raised here, after the children are stopped."""
    w = max(1, min(workers, len(fns))) if can_fork() else 1
    groups = [range(g, len(fns), w) for g in range(w)]
    children = [Deferred(partial(_run_group, fns, idx), fork=True) for idx in groups[1:]]
    out: list[Any] = [None] * len(fns)
    try:
        for i in groups[0]:
            out[i] = fns[i]()
        for idx, child in zip(groups[1:], children, strict=True):
            for i, value in zip(idx, child.result(), strict=True):
                out[i] = value
    finally:
        for child in children:
            child.cancel()
    return out
