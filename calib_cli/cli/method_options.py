"""Click options generated from the methods' ``Option`` declarations (methods/method.py):
``calib fit NAME``'s options and those of ``calib plan check``/``optimize`` that change a
prediction. Imports click and the method table only (start-up time)."""

from __future__ import annotations

import click

from calib_cli.methods.method import Option
from calib_cli.methods.registry import FITS


def _key_values(items, flag: str) -> dict:
    """KEY=NUMBER items -> {key: float}; a malformed one is a usage error."""
    import math

    out = {}
    for item in items:
        key, sep, val = item.partition("=")
        try:
            num = float(val)
        except ValueError:
            num = math.nan
        if not sep or not key.strip() or not math.isfinite(num) or num <= 0:
            raise click.UsageError(f"{flag} expects KEY=POSITIVE_NUMBER, got {item!r}")
        out[key.strip()] = num
    return out


def parse_cli_value(o: Option, value):
    """A command-line value in the option's form (usage error when malformed)."""
    if value is None or value == ():
        return None
    if o.kind == "auto_float":
        if str(value).strip().lower() == "auto":
            return "auto"
        try:
            return float(value)
        except ValueError:
            raise click.UsageError(f"{o.cli_flag} must be auto or a number, got {value!r}") from None
    if o.kind == "key_values":
        items = value if o.multiple else str(value).split(",")
        return _key_values(items, o.cli_flag) or None
    return value


def click_option(o: Option, default_none: bool = False, prefix: str = "", suffix: str = ""):
    """The click option of a method option (``default_none``: for plan check, where an
    unset option means the fit's default)."""
    kw: dict = {"help": prefix + o.help + suffix}
    if o.metavar:
        kw["metavar"] = o.metavar
    default = None if default_none else o.default
    if o.kind == "choice":
        kw.update(type=click.Choice(list(o.choices)), default=default,
                  show_default=default is not None)
    elif o.kind in ("float", "int"):
        kw.update(type=float if o.kind == "float" else int, default=default,
                  show_default=default is not None)
    elif o.kind == "auto_float":
        kw.update(default=default, show_default=default is not None)
    elif o.kind == "key_values":
        kw.update(multiple=o.multiple)
    elif o.kind in ("calibration", "text"):
        kw.update(type=click.Path(dir_okay=False))
    return click.option(o.cli_flag, o.name, **kw)


def plan_options(f):
    """The options of every method marked ``plan_check``, default unset (the fit's
    default), for ``plan check`` and ``plan optimize``."""
    seen: dict = {}
    for m in FITS.values():
        for o in m.options:
            if o.plan_check:
                seen.setdefault(o.name, (o, []))[1].append(m.name)
    for o, methods in reversed(list(seen.values())):
        f = click_option(o, default_none=True, prefix=f"{'/'.join(methods)}: ",
                         suffix=f" [fit's default: {o.default}]")(f)
    return f


def plan_option_values(method: str, values: dict) -> dict:
    """The given ``plan_options`` values parsed, for the method a plan goes to (a value
    given for another method's option is a usage error naming it)."""
    from calib_cli.design import method_of

    m = method_of(method)[0]
    names = {o.name for o in m.options}
    out = {}
    for name, v in values.items():
        if v is None or v == ():
            continue
        owner = next(x for x in FITS.values() for o in x.options if o.name == name and o.plan_check)
        if name not in names:
            raise click.UsageError(f"{owner.option(name).cli_flag} applies to {owner.name} plans "
                                   f"only (this plan goes to the {m.name} fit)")
        out[name] = parse_cli_value(m.option(name), v)
    return out
