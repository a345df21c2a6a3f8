"""``omni-sfm ... | head``: a stdout pipe closed by its reader ends the command quietly (no
BrokenPipeError traceback, exit code 141 or 0), whether the reader left before or after the
first line."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from omni_sfm.cli import EXIT_BROKEN_PIPE

ROOT = Path(__file__).resolve().parents[1]
EXE = Path(sys.executable).parent / "omni-sfm"
CAMERA = ROOT / "docs" / "examples" / "cameras" / "hyperboloid.yaml"
# argv, exit codes allowed: argparse itself swallows a failed write of --help and exits 0
COMMANDS = [(["camera", "show", str(CAMERA)], {EXIT_BROKEN_PIPE}), (["--help"], {0})]

pytestmark = pytest.mark.skipif(not EXE.is_file(), reason=f"no {EXE} (package not installed)")


def assert_quiet(stderr: str) -> None:
    assert "Traceback" not in stderr and "BrokenPipeError" not in stderr, stderr
    assert "Exception ignored" not in stderr, stderr


@pytest.mark.parametrize(("argv", "codes"), COMMANDS, ids=["camera-show", "help"])
def test_reader_gone_before_output(argv: list[str], codes: set[int]) -> None:
    """The read end is closed before the command writes anything: every write fails (the
    deterministic case of ``| head -1`` finishing first)."""
    r, w = os.pipe()
    os.close(r)
    try:
        p = subprocess.run([str(EXE), *argv], stdout=w, stderr=subprocess.PIPE, text=True,
                           cwd=ROOT, timeout=120)
    finally:
        os.close(w)
    assert_quiet(p.stderr)
    assert p.returncode in codes, (p.returncode, p.stderr)


def test_reader_gone_after_one_line() -> None:
    """A reader that takes one line and closes the pipe, as ``head -1`` does."""
    p = subprocess.Popen([str(EXE), "camera", "show", str(CAMERA)], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, cwd=ROOT)
    assert p.stdout is not None and p.stderr is not None
    first = p.stdout.readline()
    p.stdout.close()
    err = p.stderr.read()
    rc = p.wait(timeout=120)
    assert first.startswith("file:"), first
    assert_quiet(err)
    assert rc in (0, EXIT_BROKEN_PIPE), (rc, err)


def test_shell_head() -> None:
    """The report's own reproduction: ``omni-sfm camera show FILE | head -1``."""
    p = subprocess.run(["sh", "-c", f'"{EXE}" camera show "{CAMERA}" | head -1'],
                       capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert p.returncode == 0 and p.stdout.startswith("file:"), (p.stdout, p.stderr)
    assert_quiet(p.stderr)
