"""The lazily loaded command line (issue 19's start-up): a command module that
declares ``COMPLETE_COMMAND = True`` is imported alone for its command, so it
must hold every subcommand of the commands it registers."""

from __future__ import annotations

import importlib
import pkgutil

import click

import calib_cli.cli as pkg
from calib_cli.cli.main import cli, register_all


def _callback_modules(cmd, acc):
    if cmd.callback is not None:
        acc.add(cmd.callback.__module__)
    if isinstance(cmd, click.Group):
        for sub in cmd.commands.values():
            _callback_modules(sub, acc)
    return acc


def test_complete_commands_hold_all_their_subcommands():
    register_all()
    complete = []
    for info in pkgutil.iter_modules(pkg.__path__):
        if not info.name.startswith("cmd_"):
            continue
        mod = importlib.import_module(f"calib_cli.cli.{info.name}")
        if getattr(mod, "COMPLETE_COMMAND", False):
            name = info.name[4:].replace("_", "-")
            assert name in cli.commands, f"{info.name} declares COMPLETE_COMMAND but no {name!r}"
            assert _callback_modules(cli.commands[name], set()) == {mod.__name__}, info.name
            complete.append(name)
    assert {"import", "allan", "report", "show", "plan", "diagnose"} <= set(complete)


def test_show_finds_the_module_of_each_file_kind():
    """`calib show` loads alone; the file kinds other modules register (SHOWERS) are
    found through the static tree's "showers" map."""
    from calib_cli.cli import tree as index
    from calib_cli.cli.cmd_show import SHOWERS

    register_all()
    assert set(index.tree()["showers"]) == set(SHOWERS) >= {"allan", "diagnosis"}
