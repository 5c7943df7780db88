"""Output-path guard for every command (issue 15, CONTRACT.md section 7).

Each command's callback is wrapped once at start-up: the path-typed
parameters that name outputs are checked against every path-typed input of
the same command (same file, symlink, hard link: exit 2), for being writable
(exit 2) and for being a directory where a file is expected (exit 3), before
the command runs, so nothing is written. calib_cli/io/outpath.py does the
checks.
"""

from __future__ import annotations

import functools

import click

# parameter names (click's python names) that name something a command writes
OUTPUT_PARAMS = {"out", "out_dir", "plot", "plot_path", "truth_out", "log_path", "report_dir",
                 "kalibr_path"}
# per command: further outputs (record's journal is written, recover's is read)
COMMAND_OUTPUTS = {"record": {"journal_path"}, "diagnose": {"cal_out"}}
# options naming a profile by name or by path: a path is an input like any file
PROFILE_PARAMS = {"imu", "table", "chamber", "rimu_profile", "profile"}


def _flat(v):
    if v is None:
        return []
    if isinstance(v, (list, tuple)):
        return [x for y in v for x in _flat(y)]
    return [v]


def _regular_or_dir(path) -> None:
    """A device or a pipe (/dev/zero, a FIFO) is no input file: it would be read
    forever. Exit 3 naming it."""
    import os
    import stat

    from calib_cli.errors import InputError

    try:
        mode = os.stat(path).st_mode
    except (OSError, TypeError, ValueError):
        return  # missing: the command says so
    if not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):
        raise InputError("not a regular file (a device or a pipe); give a file", str(path))


def _is_file(v) -> bool:
    import os

    return isinstance(v, str) and os.path.isfile(v)


def _option_name(cmd: click.Command, name: str) -> str:
    for p in cmd.params:
        if p.name == name:
            return max(getattr(p, "opts", None) or [name.upper()], key=len)
    return name


# float options that must be > 0 (durations, windows, rates, multipliers)
POSITIVE_PARAMS = {"window_s", "multiplier", "min_static_s", "settle_window", "settle_timeout",
                   "segment_duration", "reconnect_timeout", "duration", "rate", "block",
                   "speed_dps"}


def _check_numbers(cmd: click.Command, kwargs: dict) -> None:
    """Float options: finite (no nan/inf), and > 0 where the physics says so (exit 2)."""
    import math

    for p in cmd.params:
        if not isinstance(p.type, (click.types.FloatParamType, click.FloatRange)):
            continue
        for v in _flat(kwargs.get(p.name)):
            if not isinstance(v, float):
                continue
            if not math.isfinite(v):
                raise click.BadParameter(f"must be a finite number, got {v}", param=p)
            if p.name in POSITIVE_PARAMS and v <= 0:
                raise click.BadParameter(f"must be > 0, got {v:g}", param=p)


def _wrap(cmd: click.Command) -> None:
    cb = cmd.callback
    if cb is None or getattr(cb, "_calib_guarded", False):
        return
    path_params = {p.name: p for p in cmd.params if isinstance(p.type, click.Path)}
    outs = (OUTPUT_PARAMS | COMMAND_OUTPUTS.get(cmd.name, set())) & set(path_params)

    profiles = {p.name for p in cmd.params if p.name in PROFILE_PARAMS
                and not isinstance(p.type, click.Path)}

    @functools.wraps(cb)
    def guarded(*args, **kwargs):
        from calib_cli.errors import EstimationError, InputError
        from calib_cli.io.outpath import check_output, check_outputs_apart

        _check_numbers(cmd, kwargs)

        inputs = [x for n in path_params if n not in outs for x in _flat(kwargs.get(n))]
        for x in inputs:
            _regular_or_dir(x)
        files = [x for x in inputs if _is_file(x)]
        inputs += [x for n in profiles for x in _flat(kwargs.get(n)) if _is_file(x)]
        named = []  # (option, path, directory) of every output
        for n in sorted(outs):
            for v in _flat(kwargs.get(n)):
                directory = not path_params[n].type.file_okay
                check_output(v, inputs, directory=directory, option=_option_name(cmd, n))
                named.append((_option_name(cmd, n), v, directory))
        check_outputs_apart(named, inputs)
        try:
            return cb(*args, **kwargs)
        except (EstimationError, InputError) as exc:  # the data of the one input (issue 37)
            option = isinstance(exc, InputError) and exc.message.startswith("-")  # --opt ...
            if exc.path is None and len(files) == 1 and not option:
                exc.path = str(files[0])
            raise

    guarded._calib_guarded = True
    cmd.callback = guarded


def guard_all(group: click.Group) -> None:
    for cmd in group.commands.values():
        if isinstance(cmd, click.Group):
            guard_all(cmd)
        else:
            _wrap(cmd)


def guard_one(cmd: click.Command) -> None:
    """Guard one command (a group: all its subcommands); idempotent."""
    if isinstance(cmd, click.Group):
        guard_all(cmd)
    else:
        _wrap(cmd)
