"""The ``omni-sfm`` parser: a command's own parser alone parses its arguments as the full one
does, and names the command its module is named after (``build_parser(command)``)."""

from __future__ import annotations

import pkgutil

import pytest

import omni_sfm.cli
from omni_sfm.cli import build_parser

COMMANDS = sorted(m.name[4:] for m in pkgutil.iter_modules(omni_sfm.cli.__path__)
                  if m.name.startswith("cmd_"))


def _choices(parser) -> dict:
    """The subcommands' parsers of ``parser``, by name."""
    return next(a for a in parser._actions if a.dest == "command").choices


def _subcommands(parser) -> list[str]:
    return sorted(_choices(parser))


def test_full_parser_has_every_command() -> None:
    assert _subcommands(build_parser()) == COMMANDS
    assert _subcommands(build_parser("no-such-command")) == COMMANDS  # argparse names choices


@pytest.mark.parametrize("command", COMMANDS)
def test_one_commands_parser_is_the_full_ones(command: str) -> None:
    one, full = build_parser(command), build_parser()
    assert _subcommands(one) == [command]
    assert _choices(one)[command].format_help() == _choices(full)[command].format_help()


def test_unknown_command_lists_the_commands(capsys) -> None:
    from omni_sfm.cli import main

    with pytest.raises(SystemExit) as exc:
        main(["refin"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "invalid choice: 'refin'" in err and "'refine'" in err
