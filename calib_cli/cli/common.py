"""Shared CLI plumbing: consoles, JSON, progress, output paths."""

from __future__ import annotations

import json
import sys

from rich.console import Console

from calib_cli.io.contract_json import to_jsonable  # noqa: F401  (re-exported)

# status and tables go to stderr so that --json output on stdout stays clean
err_console = Console(stderr=True, highlight=False)
out_console = Console(highlight=False)


class Ctx:
    """Global options (calib --debug --quiet ...)."""

    debug = False
    quiet = False


def interactive() -> bool:
    return sys.stderr.isatty() and not Ctx.quiet


def info(msg: str) -> None:
    if not Ctx.quiet:
        err_console.print(msg)


def print_json(obj) -> None:
    sys.stdout.write(json.dumps(to_jsonable(obj), indent=2) + "\n")


def complete_profile(kind: str):
    """A click shell_complete callback: the profile names of KIND."""

    def complete(ctx, param, incomplete):
        from click.shell_completion import CompletionItem

        from calib_cli.io.profiles import all_profiles

        return [CompletionItem(p["name"], help=p["description"])
                for p in all_profiles((kind,))
                if not p["shadowed"] and p["name"].startswith(incomplete)]

    return complete
