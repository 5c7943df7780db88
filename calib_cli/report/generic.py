"""Report sections built from a calibration's params, sigma and units alone, for
a method or an effect that has no section of its own: a new fit method gets a
readable report the day it is registered (methods/registry.py), a new effect
of the catalogue one when a fit adds it with --with."""

from __future__ import annotations

import numpy as np

from calib_cli.report.figures import parameter_figure
from calib_cli.report.items import AddedEffect, FigureItem, ReportContext, Section, Table

CAPTION = ("Each entry with its 1-sigma bar, in display units (a dimensionless matrix as its "
           "deviation from the identity, ppm; hollow: fixed by the model, no uncertainty; "
           "cross: not determined by this data). What to look for: an entry many sigma from "
           "zero is well determined; a bar wider than the value means the data hardly see it.")


def _items(cal, keys) -> list:
    return [(k, cal.params[k], cal.sigma.get(k, np.full(np.shape(cal.params[k]), np.nan)),
             cal.units.get(k, "")) for k in keys if k in cal.params]


def entry_table(cal, keys, caption: str) -> Table:
    from calib_cli.model.display import entries

    sub = {k: cal.params[k] for k in keys if k in cal.params}
    rows = [[e.name, e.value, e.sigma, e.unit] for e in entries(sub, cal.sigma, cal.units)]
    return Table(caption, ["parameter", "value", "1 sigma", "unit"], rows)


def method_section(ctx: ReportContext) -> Section:
    """The section of a method without one of its own: what it fitted, in words and
    as a figure of every parameter with its 1-sigma."""
    cal = ctx.cal
    keys = list(cal.params)
    n_free = sum(int(np.sum(np.asarray(cal.sigma.get(k, np.nan), float) > 0)) for k in keys)
    text = [f"The {cal.method} fit determined {n_free} entries of {len(keys)} parameters "
            f"({', '.join(keys) or 'none'}); the figure shows each with its 1-sigma, the "
            "table under Parameters lists them."]
    return Section(f"{cal.method} fit", text=text,
                   figures=[FigureItem("parameters", parameter_figure(
                       _items(cal, keys), f"{cal.method} fit: parameters"), CAPTION)])


def base_parameter_figure(ctx: ReportContext, added: list) -> FigureItem:
    """The base model's parameters (those no added effect owns) as a figure."""
    cal = ctx.cal
    owned = {k for e in added for k in e.keys}
    keys = [k for k in cal.params if k not in owned] or list(cal.params)
    return FigureItem("base-parameters", parameter_figure(
        _items(cal, keys), f"{cal.method}: the base model's parameters"), CAPTION)


def effect_section(ctx: ReportContext, eff: AddedEffect) -> Section:
    """An added effect without a section of its own: its parameters with 1-sigma."""
    cal = ctx.cal
    if not eff.keys:
        return Section(f"Added effect: {eff.with_arg}", text=[
            f"{eff.with_arg} was added to the model, but the calibration holds no parameter "
            "of it (a noise-model term is reported under Statistics, noise_model)."],
            figures=[base_parameter_figure(ctx, [])])
    return Section(f"Added effect: {eff.with_arg}",
                   text=[describe_effect(cal, eff)],
                   tables=[entry_table(cal, eff.keys, f"Parameters of {eff.with_arg}.")],
                   figures=[FigureItem(f"effect-{eff.name}", parameter_figure(
                       _items(cal, eff.keys), f"{eff.with_arg}: parameters"), CAPTION)])


def describe_effect(cal, eff: AddedEffect) -> str:
    """The effect's own words (Effect.describe) with its largest term."""
    from calib_cli.model.truth import effect_from_description

    try:
        return effect_from_description(eff.desc).describe(cal.params, cal.sigma) + "."
    except (TypeError, ValueError, KeyError):
        return f"{eff.with_arg}: parameters {', '.join(eff.keys)}."
