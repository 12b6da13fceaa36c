"""The ``graylight`` entry point: a command's parser comes from its module alone and parses
its command line as the whole parser does; the command table matches what the modules register."""

from __future__ import annotations

import argparse
import importlib

import pytest

from services.cli import main as cli


def _registered(module: str) -> list[str]:
    sub = argparse.ArgumentParser().add_subparsers()
    importlib.import_module(module).register(sub)
    return list(sub.choices)


def test_the_command_table_matches_the_modules() -> None:
    table = {command: module for module in cli.COMMAND_MODULES for command in _registered(module)}
    assert cli.COMMANDS == table


@pytest.mark.parametrize("argv", [
    ["tiles", "c.ply", "--out", "t", "--workers", "2"],
    ["-v", "preview", "t", "--out", "p.mp4", "--seconds", "2"],
    ["--verbose", "export", "c.ply", "--format", "laz", "--out", "c.laz"],
    ["compress", "range.npz", "--out", "r.glr"],
    ["batch", "status", "b-1"],
])  # fmt: skip
def test_a_command_s_own_parser_parses_as_the_whole_one(argv: list[str]) -> None:
    whole = vars(cli.build_parser().parse_args(argv))
    own = cli.build_parser(argv)
    assert len(own._subparsers._group_actions[0].choices) < len(cli.COMMANDS)  # only its module's
    assert {k: v for k, v in vars(own.parse_args(argv)).items() if k != "func"} == {
        k: v for k, v in whole.items() if k != "func"
    }


@pytest.mark.parametrize("argv", [[], ["--help"], ["-v"], ["tilez", "x"]])
def test_other_command_lines_get_every_command(argv: list[str]) -> None:
    assert set(cli.build_parser(argv)._subparsers._group_actions[0].choices) == set(cli.COMMANDS)


def test_an_unknown_command_is_refused_with_the_full_list(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        cli.main(["tilez", "x"])
    err = capsys.readouterr().err
    assert "invalid choice: 'tilez'" in err and "'tiles'" in err and "'merge'" in err
