"""`calib --help` and shell completion answer from the static tree
(calib_cli/cli/_tree.py) without importing numpy or the commands' modules;
the tree matches the real click tree (regenerate: python -m calib_cli.cli.index --write)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from calib_cli.cli import index, tree

ROOT = Path(__file__).resolve().parent.parent


def test_static_tree_is_current():
    current = (Path(index.__file__).parent / index.TREE_FILE).read_text(encoding="utf-8")
    assert current == index.render(index.full_tree()), (
        "calib_cli/cli/_tree.py is stale: run `python -m calib_cli.cli.index --write`")


def _run(code: str, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], env={**os.environ, **(env or {})},
                          capture_output=True, text=True, timeout=120, cwd=ROOT)


ENTRY = ("import sys\nsys.argv = ['calib'] + sys.argv[1:]\nfrom calib_cli.__main__ import run\n"
         "try:\n    run()\nexcept SystemExit:\n    pass\n"
         "print('LOADED', sorted(m for m in ('numpy', 'rich', 'h5py', 'scipy') "
         "if m in sys.modules), file=sys.stderr)\n")


def test_help_from_the_static_tree_equals_the_full_help():
    fast = subprocess.run([sys.executable, "-c", ENTRY, "--help"], capture_output=True,
                          text=True, timeout=120, cwd=ROOT)
    assert fast.returncode == 0, fast.stderr
    assert "LOADED []" in fast.stderr  # no numpy, rich, h5py or SciPy for the help list
    full = _run("from calib_cli.cli.main import main\nmain(['--help'])")
    assert fast.stdout == full.stdout
    assert "Commands:" in fast.stdout and "profiles" in fast.stdout


def _complete(words: str) -> subprocess.CompletedProcess:
    n = len(words.split()) - (0 if words.endswith(" ") else 1)
    return _run(ENTRY, {"_CALIB_COMPLETE": "bash_complete", "COMP_WORDS": words,
                        "COMP_CWORD": str(n)})


def test_completion_from_the_static_tree():
    r = _complete("calib fi")
    assert "plain,fit" in r.stdout and "LOADED []" in r.stderr
    r = _complete("calib fit tu")
    assert "plain,turntable" in r.stdout
    r = _complete("calib fit turntable --gr")
    assert "plain,--grade" in r.stdout
    r = _complete("calib fit turntable x.h5 --grade ")
    assert {"plain,mems", "plain,tactical", "plain,navigation"} <= set(r.stdout.split())
    r = _complete("calib emulate --imu ")  # profile names, with their descriptions
    assert "plain,nmea-imu" in r.stdout and "LOADED []" in r.stderr
    r = _complete("calib record --table ")
    assert "plain,manual" in r.stdout


def test_stub_tree_mirrors_every_command():
    from calib_cli.cli import main

    main.register_all()

    def names(cmd, prefix=()):
        import click

        out = {prefix}
        if isinstance(cmd, click.Group):
            ctx = click.Context(cmd)
            for n in cmd.list_commands(ctx):
                out |= names(cmd.get_command(ctx, n), prefix + (n,))
        return out

    assert names(tree.stub()) == names(main.cli)


def _paths(cmd, prefix=()):
    import click

    out = [prefix]
    if isinstance(cmd, click.Group):
        ctx = click.Context(cmd)
        for n in cmd.list_commands(ctx):
            out += _paths(cmd.get_command(ctx, n), prefix + (n,))
    return out


def test_every_subcommand_help_from_the_static_tree_equals_the_real_one():
    """`calib X [Y] --help` answers from the static tree (no command module loaded),
    word for word what the real command prints."""
    from click.testing import CliRunner

    from calib_cli.cli import main

    main.register_all()
    runner = CliRunner()
    paths = [p for p in _paths(main.cli) if p]
    assert len(paths) > 30
    for path in paths:
        real = runner.invoke(main.cli, [*path, "--help"], prog_name="calib", terminal_width=80)
        fast = runner.invoke(tree.stub(), [*path, "--help"], prog_name="calib",
                             terminal_width=80)
        assert real.exit_code == fast.exit_code == 0, path
        assert fast.output == real.output, path


def test_subcommand_help_loads_no_command_module():
    for args in (["show", "--help"], ["fit", "accel", "-h"], ["plan", "check", "--help"],
                 ["-q", "fit", "turntable", "raw.h5", "--help"]):
        r = subprocess.run([sys.executable, "-c", ENTRY, *args], capture_output=True, text=True,
                           timeout=120, cwd=ROOT)
        assert r.returncode == 0 and "Usage: calib " in r.stdout, (args, r.stderr)
        assert "LOADED []" in r.stderr, args
    # `-h` as an option's value is not a help request: the real command answers
    r = subprocess.run([sys.executable, "-c", ENTRY, "fit", "accel", "nothere.h5", "--out", "-h"],
                       capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert "nothere.h5" in r.stderr and "Usage:" not in r.stdout
