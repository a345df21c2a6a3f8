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
