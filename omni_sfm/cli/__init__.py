"""The ``omni-sfm`` command: parses, calls one library function, reports.

Each subcommand lives in its own module ``omni_sfm/cli/cmd_<name>.py`` exposing
``add_parser(subparsers)``, which adds its parser and sets ``func(args) -> int``. Modules are
discovered, so adding a command never edits this file. Known errors (:class:`OmniSfmError`,
missing files) become one line on stderr and exit code 2, never a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import os
import pkgutil
import sys
from collections.abc import Sequence

# The estimator works on many small matrices, where OpenBLAS's thread pool only adds contention
# (5-10x slower on a busy 2-core machine). Set before any command imports numpy; a value the
# user exported wins.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from omni_sfm import __version__


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(2, f"{self.prog}: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="omni-sfm",
        description="Camera motion from straight lines in omnidirectional video.",
    )
    parser.add_argument("--version", action="version", version=f"omni-sfm {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    pkg = sys.modules[__name__]
    for info in sorted(pkgutil.iter_modules(pkg.__path__), key=lambda m: m.name):
        if info.name.startswith("cmd_"):
            mod = importlib.import_module(f"{__name__}.{info.name}")
            mod.add_parser(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    from omni_sfm.errors import OmniSfmError

    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except OmniSfmError as exc:
        print(f"omni-sfm: error: {exc}", file=sys.stderr)
        return 2
    except (FileNotFoundError, IsADirectoryError, PermissionError) as exc:
        print(f"omni-sfm: error: {exc.strerror}: {exc.filename}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("omni-sfm: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
