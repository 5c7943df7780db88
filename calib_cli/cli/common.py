"""Shared CLI plumbing: consoles, JSON, progress, output paths."""

from __future__ import annotations

import json
import math
import sys

import numpy as np
from rich.console import Console

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


def to_jsonable(x):
    """numpy arrays -> nested lists, NaN/inf -> None (JSON null)."""
    if isinstance(x, dict):
        return {str(k): to_jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [to_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return to_jsonable(x.tolist())
    if isinstance(x, (np.floating, float)):
        v = float(x)
        return None if not math.isfinite(v) else v
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x


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
