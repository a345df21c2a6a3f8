"""The heavy third-party libraries, imported lazily, and how loud they may be.

Below every stage: any stage may import this module. COLMAP (pycolmap, through glog) and Open3D
log to stderr on their own; omni-sfm keeps them to errors unless the user asks for their log
(``--verbose``), so progress bars and our own one-line summaries stay readable.
"""

from __future__ import annotations

import contextlib
import importlib
from collections.abc import Iterator
from typing import Any


def open3d_module() -> Any:
    """The ``open3d`` module, typed loosely (its stubs reject numpy arrays it accepts)."""
    return importlib.import_module("open3d")


@contextlib.contextmanager
def library_logging(verbose: bool) -> Iterator[None]:
    """COLMAP's and Open3D's logging inside the block: everything with ``verbose``, else errors
    only; restored afterwards."""
    import pycolmap

    u = open3d_module().utility
    prev_colmap = pycolmap.logging.minloglevel
    level = u.VerbosityLevel.Info if verbose else u.VerbosityLevel.Error
    if not verbose:
        pycolmap.logging.minloglevel = 2  # glog: 0 INFO, 1 WARNING, 2 ERROR
    try:
        with u.VerbosityContextManager(level):
            yield
    finally:
        pycolmap.logging.minloglevel = prev_colmap


MALLOC_ENV = {"MALLOC_MMAP_THRESHOLD_": str(64 << 20), "MALLOC_TRIM_THRESHOLD_": str(256 << 20)}
"""glibc's malloc settings for the per-frame work, as environment variables (for the front
end's worker processes): arrays up to 64 MB come from the heap, and up to 256 MB of freed heap
is kept for the next frame."""


KEEP_FREED_BYTES = 1 << 30
"""What :func:`keep_freed_memory` sets in the ``omni-sfm`` process: arrays up to 1 GB come
from the heap and up to 1 GB of freed heap is kept."""


def keep_freed_memory() -> bool:
    """Tell glibc's malloc (where there is one) to keep the memory that large arrays free for
    the next ones (:data:`KEEP_FREED_BYTES`), in this process. By default glibc maps every
    array of 32 MB or more afresh and returns it to the system when freed, so the next one
    page-faults it back in: measured on a fresh process, 20 ms instead of 13 ms of CPU per
    800x600 frame's line extraction, and the joint adjustment of the 1,000-frame office walk
    (arrays of 50-160 MB each iteration) 70.1 ms a frame (median of 5 runs) with 64 MB /
    256 MB limits against 43.1 (median of 3) with these, the same results and peak memory, and
    no more a frame than at 300 frames (docs/colmap.md). Returns whether the settings were
    applied."""
    import ctypes
    import ctypes.util
    import sys

    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        m_trim_threshold, m_mmap_threshold = -1, -3  # glibc's mallopt parameters
        ok = libc.mallopt(m_mmap_threshold, KEEP_FREED_BYTES) == 1
        return bool(ok and libc.mallopt(m_trim_threshold, KEEP_FREED_BYTES) == 1)
    except (OSError, AttributeError):
        return False
