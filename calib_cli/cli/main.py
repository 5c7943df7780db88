"""The `calib` command: click group, global options, exit-code mapping."""

from __future__ import annotations

import sys

import click

from calib_cli import __version__
from calib_cli.cli.common import Ctx
from calib_cli.errors import CalibError, warnings_to

EXIT_INTERNAL = 70  # not in the contract: an unexpected error inside calib (a bug)


class _Commands(click.Group):
    """The top-level group. In a process started by the ``calib`` entry point
    (``calib_cli.__main__.run``), modules are imported on demand: a command
    whose module declares ``COMPLETE_COMMAND = True`` (all its subcommands
    live there) is loaded alone, which spares `calib import` the start-up of
    every other command (about 1 s of SciPy imports); anything else, and any
    listing (help), loads every module."""

    def get_command(self, ctx, name):
        cmd = super().get_command(ctx, name)
        if cmd is None and not _loaded:
            if not _load_one(name):
                register_all()
            cmd = super().get_command(ctx, name)
        if cmd is not None:  # output-path and number guards (issue 15), lazily loaded too
            from calib_cli.cli.guard import guard_one

            guard_one(cmd)
        return cmd

    def list_commands(self, ctx):
        register_all()
        return super().list_commands(ctx)

    def format_epilog(self, ctx, formatter):
        """Where the docs/ files the help texts name are in this install."""
        from calib_cli.docs_path import docs_dir

        formatter.write_paragraph()
        formatter.write_text(f"docs/ (named in the help texts): {docs_dir()}")

    def format_commands(self, ctx, formatter):
        """`calib --help` from the static index (cli/index.py, cli/_tree.py) while
        the commands' modules are not loaded: < 0.3 s instead of seconds."""
        if _loaded:
            return super().format_commands(ctx, formatter)
        from click.utils import make_default_short_help

        from calib_cli.cli.tree import top_level_rows

        rows = top_level_rows()
        if rows:  # as click's own format_commands lays them out
            limit = formatter.width - 6 - max(len(n) for n, _ in rows)
            with formatter.section("Commands"):
                formatter.write_dl([(n, make_default_short_help(h, limit)) for n, h in rows])

    def parse_args(self, ctx, args):
        """`-q`/`--quiet` (and `--debug`) are accepted at any position, e.g.
        `calib fit accel raw.h5 --out cal.h5 -q`: moved before the subcommand
        (not after a `--`, which ends the options)."""
        args = list(args)
        end = args.index("--") if "--" in args else len(args)
        moved = [a for a in args[:end] if a in GLOBAL_FLAGS]
        if moved:
            args = moved + [a for a in args[:end] if a not in GLOBAL_FLAGS] + args[end:]
        return super().parse_args(ctx, args)


GLOBAL_FLAGS = ("-q", "--quiet", "--debug")


@click.group(cls=_Commands, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="calib")
@click.option("--debug", is_flag=True, help="Show tracebacks on errors.")
@click.option("--quiet", "-q", is_flag=True, help="No progress or status output.")
def cli(debug: bool, quiet: bool) -> None:
    """calib: bench calibration of inertial measurement units.

    Steps are chained through HDF5 files: import/simulate/record -> raw.h5 ->
    fit -> cal.h5 -> apply/show/report. See docs/commands.md.
    """
    Ctx.debug = debug
    Ctx.quiet = quiet
    # warnings of the core (errors.warn) print as one line unless -q, for this run only
    ctx = click.get_current_context()
    ctx.with_resource(warnings_to(_print_warning))


def _print_warning(line: str) -> None:
    if not Ctx.quiet:
        from calib_cli.cli import common

        common.err_console.print(f"calib: warning: {line}", markup=False, soft_wrap=True)


_loaded = False


def register_all() -> None:
    """Each command lives in its own module ``cli/cmd_*.py``; importing it
    registers it on ``cli`` (no central list to edit when adding a command)."""
    import importlib
    import pkgutil

    import calib_cli.cli as pkg

    global _loaded
    if _loaded:
        return
    _loaded = True
    for mod in sorted(m.name for m in pkgutil.iter_modules(pkg.__path__)):
        if mod.startswith("cmd_"):
            importlib.import_module(f"calib_cli.cli.{mod}")


def _load_one(name: str) -> bool:
    """Import ``cmd_<name>`` alone; True when it holds the whole command."""
    import importlib
    import importlib.util

    modname = f"calib_cli.cli.cmd_{name.replace('-', '_')}"
    if not name.isidentifier() or importlib.util.find_spec(modname) is None:
        return False
    mod = importlib.import_module(modname)
    return bool(getattr(mod, "COMPLETE_COMMAND", False)) and name in cli.commands


import calib_cli.cli as _pkg  # noqa: E402

if not getattr(_pkg, "LAZY_COMMANDS", False):
    register_all()

from calib_cli.cli.guard import guard_all  # noqa: E402

guard_all(cli)


def _err():
    """The stderr console, made on first use (rich is not imported for --help)."""
    from calib_cli.cli import common

    return common.err_console


def main(argv=None) -> None:
    """Entry point: run the command, map failures to the contract's exit codes."""
    import warnings

    if not (Ctx.debug or "--debug" in (argv or sys.argv)):
        # numpy's RuntimeWarning text (with source lines) is not for users: a bad
        # value is reported as an error naming the file (issue 15)
        warnings.simplefilter("ignore", RuntimeWarning)
    try:
        rv = cli.main(args=argv, prog_name="calib", standalone_mode=False)
        sys.exit(rv if isinstance(rv, int) else 0)
    except CalibError as exc:
        if Ctx.debug:
            __import__("traceback").print_exc()
        _err().print(f"calib: error: {exc.line()}", markup=False, soft_wrap=True)
        sys.exit(exc.exit_code)
    except click.exceptions.Abort:
        _err().print("calib: interrupted", markup=False)
        sys.exit(130)
    except KeyboardInterrupt:
        _err().print("calib: interrupted", markup=False)
        sys.exit(130)
    except click.UsageError as exc:  # one line, with where to look for help
        # click lists a Choice's values one per line ("Choose from:\n\taccel,\n\t...")
        msg = " ".join(exc.format_message().split())
        if isinstance(exc, click.BadParameter) and "is a directory" in msg:
            # a directory where a file is expected: bad input (exit 3)
            _err().print(f"calib: error: {msg}", markup=False, soft_wrap=True)
            sys.exit(3)
        where = exc.ctx.command_path if exc.ctx is not None else "calib"
        _err().print(f"calib: error: {msg} (see {where} --help)", markup=False,
                          soft_wrap=True)
        sys.exit(exc.exit_code)
    except click.ClickException as exc:
        exc.show()
        sys.exit(exc.exit_code)
    except click.exceptions.Exit as exc:
        sys.exit(exc.exit_code)
    except SystemExit:
        raise
    except BrokenPipeError:
        sys.exit(0)
    except (OSError, MemoryError, RecursionError) as exc:  # an input the OS or numpy refused
        if Ctx.debug:
            __import__("traceback").print_exc()
        where = getattr(exc, "filename", None)
        what = getattr(exc, "strerror", None) or type(exc).__name__
        if isinstance(exc, MemoryError):
            what = "input too large for memory"
        elif isinstance(exc, RecursionError):
            what = "input nested too deeply"
        _err().print(f"calib: error: {where + ': ' if where else ''}{what}", markup=False,
                          soft_wrap=True)
        sys.exit(3)
    except Exception as exc:  # a bug: one line, traceback only with --debug
        if Ctx.debug or "--debug" in (argv or sys.argv):
            __import__("traceback").print_exc()
        _err().print(f"calib: internal error: {type(exc).__name__}: {exc} "
                          "(run with --debug for the traceback)", markup=False, soft_wrap=True)
        sys.exit(EXIT_INTERNAL)
