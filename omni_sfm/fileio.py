"""Output that appears complete or not at all, and small readers with one-line errors."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from collections import deque
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from omni_sfm.errors import OmniSfmError


def _json_default(o: Any) -> Any:
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def dumps_json(obj: Any) -> str:
    """JSON text with numpy arrays and scalars converted, indented for people to read."""
    return json.dumps(obj, indent=2, default=_json_default) + "\n"


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def atomic_write_text(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary file in the same folder and a rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
        # mkstemp creates 0600; give the file the permissions an ordinary open() would
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def read_json(path: Path, what: str = "JSON file") -> Any:
    """Parse a JSON file, turning every failure into a one-line :class:`OmniSfmError`."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise OmniSfmError(f"{path}: {what} not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise OmniSfmError(f"{path}: cannot read {what}: {exc}") from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise OmniSfmError(
            f"{path}: malformed {what}: {exc.msg} at line {exc.lineno} column {exc.colno}"
        ) from None


def check_output_dir(path: Path, *, overwrite: bool, inputs: tuple[Path | None, ...] = ()
                     ) -> None:
    """Refuse an output folder that exists and is not empty, unless ``overwrite``, and one that
    is one of ``inputs``, lies inside one or holds one (writing it would destroy the input)."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise OmniSfmError(f"{path}: output path exists and is not a folder")
    out = path.resolve()
    for inp in inputs:
        if inp is None:
            continue
        src = Path(inp).resolve()
        if out == src:
            raise OmniSfmError(f"{path}: the output folder is the input; choose another "
                               "--output")
        if src in out.parents:
            raise OmniSfmError(f"{path}: the output folder would be inside the input {inp}; "
                               "choose another --output")
        if out in src.parents:
            raise OmniSfmError(f"{path}: the output folder holds the input {inp}; choose "
                               "another --output")
    if path.is_dir() and any(path.iterdir()) and not overwrite:
        raise OmniSfmError(f"{path}: output folder exists and is not empty (use --overwrite)")


def stored_path(target: Path | str, folder: Path | str) -> str:
    """How an output folder records a path it depends on, so that the folder can be moved:
    relative to the folder when ``target`` lies inside it, else absolute."""
    target, folder = Path(target).resolve(), Path(folder).resolve()
    if folder == target or folder in target.parents:
        return target.relative_to(folder).as_posix()
    return str(target)


def resolve_stored(text: str, folder: Path | str) -> Path:
    """The path that :func:`stored_path` recorded in ``folder`` (relative ones are relative to
    ``folder``, whatever the current directory)."""
    p = Path(text)
    return p if p.is_absolute() else Path(folder) / p


@contextlib.contextmanager
def atomic_output_dir(path: Path, *, overwrite: bool = False,
                      inputs: tuple[Path | None, ...] = ()) -> Iterator[Path]:
    """Yield a temporary folder that becomes ``path`` only if the block finishes.

    On any exception the temporary folder is removed and ``path`` is left as it was, so a
    failed run never leaves an output folder that looks complete. An existing non-empty
    ``path`` is refused unless ``overwrite``; an existing one is replaced as a whole. An output
    that is, holds or lies inside one of ``inputs`` is refused (:func:`check_output_dir`).
    """
    path = Path(path)
    check_output_dir(path, overwrite=overwrite, inputs=inputs)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".partial", dir=path.parent))
    os.chmod(tmp, 0o777 & ~_umask())  # mkdtemp creates 0700; outputs are for people to share
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if path.exists():
        old = path.with_name(f".{path.name}.old-{os.getpid()}")
        os.replace(path, old)
        os.replace(tmp, path)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.replace(tmp, path)


class BackgroundWrites:
    """Writes of one file each (``fn(*args)``) run in up to ``threads`` threads beside the
    caller, at most ``pending`` queued or running at a time (:meth:`submit` first waits for the
    oldest beyond that: the memory they hold is bounded); the first error is raised in the
    caller, at the next :meth:`submit` or at :meth:`wait`. Meant for OpenCV's image encoders,
    which release the GIL: a PNG of an 800x600 frame takes 10-30 ms of CPU that the caller
    need not wait for. Use as a context manager: leaving it waits for every write (none more
    is started after an error) and stops the threads."""

    def __init__(self, threads: int = 1, pending: int = 8) -> None:
        from concurrent.futures import Future, ThreadPoolExecutor

        self._pool = ThreadPoolExecutor(max(1, threads), thread_name_prefix="omni-sfm-write")
        self._futures: deque[Future[Any]] = deque()
        self._pending = max(1, pending)

    def submit(self, fn: Callable[..., Any], *args: Any) -> None:
        while len(self._futures) >= self._pending:
            self._futures.popleft().result()
        self._futures.append(self._pool.submit(fn, *args))

    def wait(self) -> None:
        """Wait for every write submitted; raises the first one's error."""
        while self._futures:
            self._futures.popleft().result()

    def close(self) -> None:
        """Drop the writes not started, wait for those running, stop the threads."""
        for f in self._futures:
            f.cancel()
        self._futures.clear()
        self._pool.shutdown(wait=True)

    def __enter__(self) -> BackgroundWrites:
        return self

    def __exit__(self, exc_type: object, *_: object) -> None:
        try:
            if exc_type is None:
                self.wait()
        finally:
            self.close()
