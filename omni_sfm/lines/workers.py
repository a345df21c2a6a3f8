"""Line extraction in worker processes, for :func:`omni_sfm.lines.frontend.track_lines`.

Each worker is ``python -m omni_sfm.lines.workers``, started with the interpreter that runs
omni-sfm: it reads a pickled :class:`~omni_sfm.lines.extract.LineExtractor` on stdin, then
grey frames one at a time, and writes back each frame's ``(lines, wall s, CPU s)``. Frames go
to the workers in turn (frame ``k`` to worker ``k mod N``) and the results are taken in frame
order, so the output does not depend on the number of workers. Each worker holds at most one
frame: the caller hands it the next only after taking its result, so neither side can block
the other on a full pipe.

Plain subprocesses rather than :mod:`multiprocessing`: a forked child of a process whose OpenCV
thread pool is running hangs in its first OpenCV call, and a spawned one runs the caller's main
script again (which a user's script without ``if __name__ == "__main__"`` does not survive).
"""

from __future__ import annotations

import contextlib
import os
import pickle
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from types import TracebackType
from typing import IO, Any

import numpy as np

from omni_sfm.errors import OmniSfmError
from omni_sfm.libs import MALLOC_ENV
from omni_sfm.lines.extract import ExtractedLines, LineExtractor

Timed = tuple[ExtractedLines, float, float]
"""One frame's lines, the extraction's wall seconds and its CPU seconds (of the thread that
ran it)."""


def extract_timed(extractor: LineExtractor, gray: np.ndarray) -> Timed:
    """The lines of one grey frame, with the wall and CPU seconds it took."""
    t, c = time.perf_counter(), time.thread_time()
    lines = extractor.extract(gray)
    return lines, time.perf_counter() - t, time.thread_time() - c


class ExtractionWorkers:
    """``count`` worker processes extracting lines with ``extractor`` (a context manager).

    :meth:`submit` hands a frame to the next worker in turn; :meth:`result` returns the oldest
    submitted frame's lines. At most ``count`` frames are in flight.
    """

    def __init__(self, extractor: LineExtractor, count: int) -> None:
        if count < 1:
            raise ValueError(f"need at least one worker, got {count}")
        self.count = count
        self._procs: list[subprocess.Popen[bytes]] = []
        self._logs: list[IO[bytes]] = []
        self._sent = 0
        self._taken = 0
        blob = pickle.dumps(extractor, protocol=pickle.HIGHEST_PROTOCOL)
        env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1",
               "MKL_NUM_THREADS": "1", **MALLOC_ENV}
        # the workers import omni_sfm from where this process did, installed or not
        root = str(Path(__file__).resolve().parents[2])
        env["PYTHONPATH"] = os.pathsep.join([root, *filter(None, [env.get("PYTHONPATH")])])
        try:
            for _ in range(count):
                log = tempfile.TemporaryFile()  # noqa: SIM115 (closed in close())
                self._logs.append(log)
                proc = subprocess.Popen([sys.executable, "-m", "omni_sfm.lines.workers"],
                                        stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                        stderr=log, env=env)
                self._procs.append(proc)
                self._send(proc, blob)
        except BaseException:
            self.close()
            raise

    def __enter__(self) -> ExtractionWorkers:
        return self

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    @property
    def in_flight(self) -> int:
        return self._sent - self._taken

    def submit(self, gray: np.ndarray) -> None:
        """Hand the next frame to its worker (at most ``count`` in flight)."""
        if self.in_flight >= self.count:
            raise RuntimeError("every worker holds a frame: take a result first")
        proc = self._procs[self._sent % self.count]
        self._send(proc, pickle.dumps(np.ascontiguousarray(gray),
                                      protocol=pickle.HIGHEST_PROTOCOL))
        self._sent += 1

    def result(self) -> Timed:
        """The oldest submitted frame's lines (frames come back in the order submitted)."""
        if self.in_flight == 0:
            raise RuntimeError("no frame in flight")
        k = self._taken % self.count
        proc = self._procs[k]
        assert proc.stdout is not None
        try:
            kind, value = pickle.load(proc.stdout)
        except (EOFError, pickle.UnpicklingError, OSError) as exc:
            raise OmniSfmError(f"a line extraction worker stopped: {self._why(k) or exc}") \
                from exc
        self._taken += 1
        if kind == "error":
            raise OmniSfmError(f"line extraction failed in a worker: {value}")
        return value

    def _send(self, proc: subprocess.Popen[bytes], blob: bytes) -> None:
        assert proc.stdin is not None
        try:
            proc.stdin.write(blob)
            proc.stdin.flush()
        except OSError as exc:
            k = self._procs.index(proc)
            raise OmniSfmError(f"a line extraction worker stopped: {self._why(k) or exc}") \
                from exc

    def _why(self, k: int) -> str:
        """The last line the worker wrote on stderr."""
        proc, log = self._procs[k], self._logs[k]
        try:
            proc.wait(timeout=5)
            log.seek(0)
            lines = log.read().decode(errors="replace").strip().splitlines()
        except (OSError, subprocess.TimeoutExpired):
            return ""
        return lines[-1] if lines else (f"exit code {proc.returncode}"
                                        if proc.returncode is not None else "")

    def close(self) -> None:
        """Stop the workers: they end when their input closes, and one still writing a result
        nobody will read (after an error here) ends when its output closes."""
        for proc in self._procs:
            for pipe in (proc.stdin, proc.stdout):
                try:
                    if pipe is not None:
                        pipe.close()
                except OSError:
                    pass
        for proc in self._procs:
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        for log in self._logs:
            log.close()
        self._procs, self._logs = [], []


def _serve(inp: IO[bytes], out: IO[bytes]) -> None:
    """The worker's loop: an extractor, then frames until the input closes."""
    import cv2

    cv2.setNumThreads(1)  # the processes are the parallelism
    extractor = pickle.load(inp)
    while True:
        try:
            gray = pickle.load(inp)
        except EOFError:
            return
        reply: tuple[str, Any]
        try:
            reply = ("ok", extract_timed(extractor, gray))
        except Exception as exc:  # the caller raises it with the frame's context
            reply = ("error", f"{type(exc).__name__}: {exc}")
        pickle.dump(reply, out, protocol=pickle.HIGHEST_PROTOCOL)
        out.flush()


def main() -> None:
    # the protocol owns the real stdout; anything printed goes to stderr
    out = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)  # C-level output too
    sys.stdout = sys.stderr
    try:
        _serve(sys.stdin.buffer, out)
    except (KeyboardInterrupt, BrokenPipeError):  # Ctrl-C, or the caller stopped reading
        pass
    finally:
        with contextlib.suppress(BrokenPipeError):
            out.close()


if __name__ == "__main__":
    main()
