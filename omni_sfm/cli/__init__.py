"""The ``omni-sfm`` command: parses, calls one library function, reports.

Each subcommand lives in its own module ``omni_sfm/cli/cmd_<name>.py`` exposing
``add_parser(subparsers)``, which adds its parser and sets ``func(args) -> int``. Modules are
discovered, so adding a command never edits this file. Known errors (:class:`OmniSfmError`,
missing files) become one line on stderr and exit code 2, never a traceback; a stdout pipe
closed by its reader (``omni-sfm ... | head``) ends the command quietly with exit code 141.
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


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The ``omni-sfm`` parser: every subcommand, or only ``command``'s where a module
    ``cmd_<command>`` exists (each command's parser imports the options it shows as defaults, so
    building one parser saves the other commands' imports: about half a second a call)."""
    parser = _Parser(
        prog="omni-sfm",
        description="Camera motion from straight lines in omnidirectional video.",
    )
    parser.add_argument("--version", action="version", version=f"omni-sfm {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    pkg = sys.modules[__name__]
    names = sorted(m.name for m in pkgutil.iter_modules(pkg.__path__) if m.name.startswith("cmd_"))
    if f"cmd_{command}" in names:
        names = [f"cmd_{command}"]
    for name in names:
        importlib.import_module(f"{__name__}.{name}").add_parser(sub)
    return parser


# Exit status when the reader of our stdout went away (``omni-sfm ... | head``): 128 + SIGPIPE,
# what the shell reports for cat, grep and the like killed by SIGPIPE in that situation. Not 0,
# since not all the output was delivered (``set -o pipefail`` sees us like those tools), and not
# an error message either: a reader closing the pipe early is its choice, not our failure.
EXIT_BROKEN_PIPE = 141


def _stdout_to_devnull() -> None:
    """Point file descriptor 1 at /dev/null, so the interpreter's flush of what is left in
    ``sys.stdout`` at exit does not raise BrokenPipeError again (the Python docs' recipe for
    SIGPIPE, ``signal`` module)."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError):  # stdout without a descriptor (replaced, closed)
        pass


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``omni-sfm`` with ``argv`` (default ``sys.argv[1:]``); the exit status.

    0 on success, 2 for known errors, 130 on Ctrl-C, :data:`EXIT_BROKEN_PIPE` when stdout is a
    pipe its reader closed (no traceback; the output is flushed here, where that can be caught,
    not at interpreter exit).
    """
    try:
        try:
            code = _main(argv)
        finally:
            sys.stdout.flush()
    except BrokenPipeError:
        _stdout_to_devnull()
        return EXIT_BROKEN_PIPE
    return code


def _main(argv: Sequence[str] | None) -> int:
    from omni_sfm.errors import OmniSfmError
    from omni_sfm.libs import keep_freed_memory

    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(argv[0] if argv else None)
    args = parser.parse_args(argv)
    keep_freed_memory()  # the per-frame stages run faster without giving memory back each time
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
