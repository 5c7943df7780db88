"""Shared CLI plumbing: consoles, JSON, progress, output paths."""

from __future__ import annotations

import json
import sys

# status and tables go to stderr so that --json output on stdout stays clean.
# err_console and out_console (rich Consoles) are made on first use (module
# __getattr__ below): `calib --help` and shell completion do not import rich or
# numpy (< 0.3 s, benchmarks/bench_cli.py).
_CONSOLES: dict = {}


def __getattr__(name):
    if name == "to_jsonable":  # re-exported from io/contract_json.py, which loads numpy
        from calib_cli.io.contract_json import to_jsonable

        return to_jsonable
    if name in ("err_console", "out_console"):
        if name not in _CONSOLES:
            from rich.console import Console

            stream = sys.stderr if name == "err_console" else sys.stdout
            # a pipe or a log file (CI): tables at their full width, never cut to 80
            # columns ("accel_K[0,…"); a terminal: its own width
            width = None if _isatty(stream) else FULL_WIDTH
            _CONSOLES[name] = Console(stderr=name == "err_console", highlight=False,
                                      width=width)
        return _CONSOLES[name]
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


FULL_WIDTH = 1000  # columns of a console whose stream is not a terminal


def _isatty(stream) -> bool:
    try:
        return stream.isatty()
    except (AttributeError, ValueError):
        return False


class Ctx:
    """Global options (calib --debug --quiet ...)."""

    debug = False
    quiet = False


def interactive() -> bool:
    return sys.stderr.isatty() and not Ctx.quiet


def info(msg: str) -> None:
    if not Ctx.quiet:
        __getattr__("err_console").print(msg)


def print_json(obj) -> None:
    from calib_cli.io.contract_json import to_jsonable

    sys.stdout.write(json.dumps(to_jsonable(obj), indent=2) + "\n")


def output_json(path, kind: str, warnings=(), extra: dict | None = None) -> None:
    """The --json object of a command that writes one file (import, simulate,
    apply, export): {"output", "kind", "sha256", "warnings"} on stdout alone,
    and the command's own keys ``extra`` after them."""
    import hashlib

    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    print_json({"output": str(path), "kind": kind, "sha256": h.hexdigest(),
                "warnings": [str(w) for w in warnings], **(extra or {})})


def json_output_option(f):
    """`--json`: the output object of output_json on stdout (status stays on stderr)."""
    import click

    return click.option("--json", "as_json", is_flag=True,
                        help='Print {"output", "kind", "sha256", "warnings"} of the written '
                             "file as JSON on stdout and nothing else there.")(f)


def complete_profile(kind: str):
    """A click shell_complete callback: the profile names of KIND."""

    def complete(ctx, param, incomplete):
        from click.shell_completion import CompletionItem

        from calib_cli.io.profiles import all_profiles

        return [CompletionItem(p["name"], help=p["description"])
                for p in all_profiles((kind,))
                if not p["shadowed"] and p["name"].startswith(incomplete)]

    complete.calib_profile_kind = kind  # recorded in cli/_tree.py (cli/index.py)
    return complete
