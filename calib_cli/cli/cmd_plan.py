"""calib plan check | make | optimize: experiment design (docs/plan.md)."""

from __future__ import annotations

import re

import click
import numpy as np

from calib_cli.cli.common import err_console, info, json_output_option, output_json, print_json
from calib_cli.cli.main import cli
from calib_cli.cli.method_options import plan_option_values, plan_options
from calib_cli.errors import InputError
from calib_cli.methods.registry import plan_method_names
from calib_cli.units import SUFFIXES

COMPLETE_COMMAND = True  # every subcommand lives here: loaded alone (cli/main.py)

_NOISE_RE = re.compile(r"^\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*([A-Za-z/^0-9]*)\s*$")
_ACCEL_UNITS = {"": 1.0, "m/s^2": 1.0, "mps2": 1.0, "g": 9.80665, "mg": SUFFIXES["_mg"],
                "ug": SUFFIXES["_ug"]}
_GYRO_UNITS = {"": 1.0, "rad/s": 1.0, "rps": 1.0, "mrad/s": 1e-3, "urad/s": 1e-6,
               "dps": SUFFIXES["_dps"], "deg/s": SUFFIXES["_dps"], "dph": SUFFIXES["_dph"],
               "deg/h": SUFFIXES["_dph"]}


def parse_noise(text: str, sensor: str) -> float:
    """'8mg' -> m/s^2, '0.05dps' -> rad/s; a bare number is SI."""
    units = _ACCEL_UNITS if sensor == "accel" else _GYRO_UNITS
    m = _NOISE_RE.match(text or "")
    if not m or m.group(2).lower() not in units:
        raise click.BadParameter(f"{text!r}: a number with an optional unit "
                                 f"({', '.join(u for u in units if u)})")
    v = float(m.group(1)) * units[m.group(2).lower()]
    if not np.isfinite(v) or v <= 0:
        raise click.BadParameter(f"{text!r} must be positive")
    return v


@cli.group("plan")
def plan_group():
    """Experiment design: predict what a plan delivers, make plans (docs/plan.md)."""


def _noise(plan, like, accel_noise, gyro_noise, rate, truth=None):
    from calib_cli.design import Noise, default_noise, noise_like

    if like and (accel_noise or gyro_noise or rate):
        raise click.UsageError("--like takes the noise and rate from the recording: give "
                               "either --like or --accel-noise/--gyro-noise/--rate")
    if like:
        from calib_cli.io.h5 import read_raw

        rec = read_raw(like)
        nz = noise_like(rec, like)
        n = len(plan.rimu_el0) if plan.kind == "rimu" else 3
        if len(nz.accel) != n:
            raise InputError(f"the recording has {len(nz.accel)} accelerometer channels, the "
                             f"plan's unit {n}", like)
        return nz
    d = default_noise(plan, rate, truth)
    if accel_noise is None and gyro_noise is None:
        return d
    a = d.accel if accel_noise is None else np.full(len(d.accel), parse_noise(accel_noise,
                                                                             "accel"))
    g = d.gyro if gyro_noise is None else np.full(len(d.gyro), parse_noise(gyro_noise, "gyro"))
    return Noise(a, g, d.rate, "stated")


def render_check(pr, plan_path: str) -> None:
    """The predicted 1-sigma of every entry as `calib fit` prints its result (display
    units, "fixed", "unobservable"), the noise assumed, and the correlation of the
    determined entries explained."""
    from rich.table import Table

    from calib_cli.design import condition_details
    from calib_cli.io.escape import term_text
    from calib_cli.model.display import DPH, MG, num, sigma_entries

    res = pr.result
    t = Table(title=term_text(f"plan check {plan_path}: method {pr.method}, {pr.duration:.0f} s "
                              "recorded"), show_lines=False)
    for c in ("parameter", "predicted 1 sigma", "unit"):
        t.add_column(c)
    for k, s in res.sigma.items():
        s = np.asarray(s, float)
        for e in sigma_entries(k, None, s, res.units.get(k, "")):
            mat = e.sigma.endswith(" ppm")
            t.add_row(term_text(e.name), e.sigma[:-4] if mat else e.sigma,
                      "ppm" if mat else term_text(e.unit))
    err_console.print(t)
    nz = pr.noise
    info(f"noise per sample at {nz.rate:g} Hz ({nz.source}): accel "
         f"{num(float(np.mean(nz.accel)) * MG, 3)} mg, gyro "
         f"{num(float(np.mean(nz.gyro)) * DPH, 3)} deg/h")
    cd = condition_details(res)
    info(condition_line(cd))
    if pr.unobservable:
        info(f"[yellow]unobservable:[/] {', '.join(pr.unobservable)}")
    if pr.weak:
        info(f"[yellow]weak:[/] {', '.join(pr.weak)}")
    for i, s in enumerate(pr.suggestions, 1):
        fx = f"; makes observable: {', '.join(s['fixes'])}" if s["fixes"] else ""
        info(f"suggestion {i}: {s['add']}{fx}")


WEAK_CONDITION = 1e4  # above: some combinations of the entries are poorly separated


def condition_line(cd: dict) -> str:
    """The condition number of the correlation of the determined entries, in words."""
    from calib_cli.model.display import num

    c = cd["condition_determined"]
    line = (f"correlation of the determined entries: condition number {num(c, 3)} (1: "
            f"independent; above {WEAK_CONDITION:.0e} some combinations are poorly separated")
    line += (")" if c <= WEAK_CONDITION else "): [yellow]poorly separated[/]")
    if cd["dependencies"]:
        line += (f"; {cd['dependencies']} exact linear dependencies among "
                 f"{', '.join(cd['dependent_keys'])} left out (combinations the model fixes by "
                 "construction, e.g. a lever arm's two free components written in three body "
                 "axes; not a weakness of the plan)")
    mc = cd.get("most_correlated")
    if mc:
        line += f"; most correlated: {mc[0]} and {mc[1]} (r = {mc[2]:+.2f})"
    return line + "."


def check_json(pr) -> dict:
    res = pr.result
    return {"method": pr.method, "params": res.params, "sigma": res.sigma,
            "unobservable": pr.unobservable,
            "suggestions": [{k: v for k, v in s.items() if k != "score"} for s in pr.suggestions],
            "weak": pr.weak, "condition": pr.condition, "units": res.units,
            "condition_details": _condition_json(res),
            "duration_s": pr.duration,
            "noise": {"accel": pr.noise.accel, "gyro": pr.noise.gyro,
                      "sample_rate_hz": pr.noise.rate, "source": pr.noise.source}}


def _condition_json(res) -> dict:
    from calib_cli.design import condition_details

    cd = condition_details(res)
    return {k: (None if isinstance(v, float) and not np.isfinite(v) else v)
            for k, v in cd.items()}


@plan_group.command("check")
@click.argument("plan", type=click.Path(dir_okay=False))
@click.option("--like", type=click.Path(dir_okay=False),
              help="Take the noise levels and the sample rate from this recording.")
@click.option("--accel-noise", help="Accelerometer noise, 1-sigma per sample (SI, or 8mg, 20ug).")
@click.option("--gyro-noise", help="Gyro noise, 1-sigma per sample (SI, or 0.05dps, 3dph).")
@click.option("--rate", type=float, help="Sample rate, Hz (default: the plan's sample_rate_hz).")
@click.option("--truth", "truth_path", type=click.Path(dir_okay=False),
              help="Predict at this truth model (default: a neutral unit, K = I, biases 0).")
@click.option("--method", type=click.Choice(plan_method_names()), default="auto",
              show_default=True,
              help="The fit to predict (auto: as fit would choose; a static plan with turns "
                   "goes to fit gyro, one with chamber setpoints to fit thermal).")
@plan_options
@click.option("--no-suggest", is_flag=True, help="Skip the ranked additions (faster).")
@click.option("--json", "as_json", is_flag=True, help="Print the prediction as JSON.")
def plan_check_cmd(plan, like, accel_noise, gyro_noise, rate, truth_path, method, no_suggest,
                   as_json, **method_options):
    """Predict the 1-sigma of every parameter PLAN's fit will report, the
    unobservable ones, and the additions that help most."""
    from calib_cli.design import check, resolve_method
    from calib_cli.io.plan import load_plan
    from calib_cli.io.truth import load_truth
    from calib_cli.plan import plan_layout

    if rate is not None and rate <= 0:
        raise click.BadParameter("--rate must be positive")
    p = load_plan(plan)
    opts = plan_option_values(resolve_method(p, method), method_options)
    truth = load_truth(truth_path, plan_layout(p)) if truth_path else None
    nz = _noise(p, like, accel_noise, gyro_noise, rate, truth)
    from calib_cli.cli.progress import bar

    with bar("plan check"):
        pr = check(p, method, nz, truth, opts, suggestions=not no_suggest)
    if as_json:
        print_json(check_json(pr))
    else:
        render_check(pr, plan)


def _vec(text, n, name):
    try:
        v = [float(x) for x in str(text).split(",")]
    except ValueError:
        raise click.BadParameter(f"{name} must be {n} comma-separated numbers") from None
    if len(v) != n or not all(np.isfinite(v)):
        raise click.BadParameter(f"{name} must be {n} comma-separated numbers")
    return v


@plan_group.command("make")
@click.argument("method", type=click.Choice(["static", "ferraris", "align", "turntable",
                                             "rimu", "thermal"]))
@click.option("--out", required=True, type=click.Path(dir_okay=False))
@click.option("--positions", type=click.Choice(["6", "12", "18", "24"]), default="12",
              show_default=True, help="static: number of positions.")
@click.option("--fit", "fit_method", type=click.Choice(["vector", "scalar"]), default="vector",
              show_default=True, help="static: known attitudes (vector) or spread unknown "
                                      "ones (scalar).")
@click.option("--duration", type=float, help="Seconds per position (static 10, ferraris 10, "
                                             "align 300, rimu 10, thermal soak 60, ramp 120) "
                                             "or per axial cycle (turntable 600).")
@click.option("--rate", "sample_rate", type=float, help="Sample rate, Hz (100; align 50; "
                                                        "thermal 10).")
@click.option("--turn-duration", type=float, default=10.0, show_default=True,
              help="ferraris: seconds per 360 deg turn.")
@click.option("--axis", default="0,0,1", show_default=True, help="align: turn axis (body).")
@click.option("--angle", type=float, default=120.0, show_default=True,
              help="align: turn angle, deg.")
@click.option("--start", default="0.8,-0.5,30", show_default=True,
              help="align: attitude of position 1 (roll,pitch,yaw deg) for simulate.")
@click.option("--latitude", type=float, default=32.0, show_default=True,
              help="align: site latitude, deg.")
@click.option("--profile", "rimu_profile", default="tetrahedron", show_default=True,
              help="rimu: geometry profile.")
@click.option("--table-rate", type=float, default=10.0, show_default=True,
              help="rimu: table rate in each position, deg/s (0: static).")
@click.option("--tilted/--no-tilted", default=False, help="turntable: add the 6 tilted cycles.")
@click.option("--tilt", "tilt_deg", type=float, default=5.0, show_default=True,
              help="turntable: tilt of the tilted cycles, deg.")
@click.option("--tilted-duration", type=float, default=300.0, show_default=True,
              help="turntable: seconds per tilted cycle.")
@click.option("--max-rate", type=float, default=200.0, show_default=True,
              help="turntable: the table's max rate, deg/s.")
@click.option("--max-accel", type=float, default=200.0, show_default=True,
              help="turntable: the table's max angular acceleration, deg/s^2.")
@click.option("--max-duration", type=float, help="turntable: the longest run, s.")
@click.option("--rate-profile", "rate_family", type=click.Choice(["steps", "smooth"]),
              default="steps", show_default=True, help="turntable: rate profile family.")
@click.option("--design", type=click.Choice(["soak", "ramp"]), default="soak",
              show_default=True, help="thermal: soak steps, or a ramp in a few positions.")
@click.option("--temps", type=click.IntRange(5, 7), default=7, show_default=True,
              help="thermal soak: number of temperatures.")
@click.option("--temp-range", default="-40,85", show_default=True,
              help="thermal: LO,HI degC.")
@click.option("--soak", type=float, help="thermal: seconds of the soak segment at each "
                                         "temperature (soak 1800; ramp 6 x --unit-tau).")
@click.option("--ramp-dpm", type=float, help="thermal: chamber ramp rate, degC/min (soak 3, "
                                             "ramp 1).")
@click.option("--unit-tau", type=float, help="thermal: the unit's thermal time constant for "
                                             "simulate, s (soak 300, ramp 120).")
@click.option("--ramp-positions", type=click.IntRange(3, 6), default=6, show_default=True,
              help="thermal ramp: positions visited in turn.")
@click.option("--cycles", type=click.Choice(["heat", "heat-cool"]), default="heat-cool",
              show_default=True, help="thermal ramp: heat only, or heat then cool.")
@json_output_option
def plan_make_cmd(method, out, positions, fit_method, duration, sample_rate, turn_duration, axis,
                  angle, start, latitude, rimu_profile, table_rate, tilted, tilt_deg,
                  tilted_duration, max_rate, max_accel, max_duration, rate_family, design,
                  temps, temp_range, soak, ramp_dpm, unit_tau, ramp_positions, cycles,
                  as_json=False):
    """Write a plan of METHOD's family (its parameters in a [generator] table)."""
    from calib_cli.io.h5 import atomic_path
    from calib_cli.io.plan import parse_plan
    from calib_cli.sim import plan_make as pm

    kw = {}
    if sample_rate is not None:
        if sample_rate <= 0:
            raise click.BadParameter("--rate must be positive")
        kw["rate"] = sample_rate
    if duration is not None:
        if duration <= 0:
            raise click.BadParameter("--duration must be positive")
        kw["duration"] = duration
    if method == "static":
        kw.update(n=int(positions), method=fit_method)
    elif method == "ferraris":
        kw.update(turn_duration=turn_duration)
    elif method == "align":
        kw.update(axis=_vec(axis, 3, "--axis"), angle=angle, start=_vec(start, 3, "--start"),
                  latitude=latitude)
    elif method == "rimu":
        kw.update(profile=rimu_profile, table_rate=table_rate)
    elif method == "thermal":
        kw.update(design=design, temps=temps, temp_range=_vec(temp_range, 2, "--temp-range"),
                  soak=soak, ramp_dpm=ramp_dpm, unit_tau=unit_tau, positions=ramp_positions,
                  cycles=cycles)
    else:
        kw.update(tilted=tilted, tilt_deg=tilt_deg, tilted_duration=tilted_duration,
                  max_rate=max_rate, max_accel=max_accel, max_duration=max_duration,
                  profile=rate_family)
    try:
        d, warning = pm.make(method, **kw)
    except InputError as exc:  # a generator refuses its options: a usage error
        raise click.UsageError(exc.message) from None
    text = pm.to_toml(d, header=f"made by: calib plan make {method}")
    parse_plan(text, out)  # what is written must load
    with atomic_path(out) as tmp:
        with open(tmp, "w", encoding="utf-8") as fh:
            fh.write(text)
    if warning:
        info(f"[yellow]warning:[/] {warning}")
    info(f"{method} plan, {len(d['segment'])} segments -> {out}")
    if as_json:
        output_json(out, "plan", [warning] if warning else [])


@plan_group.command("optimize")
@click.argument("plan", type=click.Path(dir_okay=False))
@click.option("--target", "targets", multiple=True, required=True,
              help="KEY[.diag|.offdiag]=SIGMA (SI), e.g. accel_K.diag=50e-6; repeatable.")
@click.option("--max-duration", type=float, help="Refuse plans longer than this, s.")
@click.option("--out", type=click.Path(dir_okay=False), help="Write the optimized plan here.")
@click.option("--like", type=click.Path(dir_okay=False),
              help="Take the noise levels and the sample rate from this recording.")
@click.option("--accel-noise", help="Accelerometer noise, 1-sigma per sample (SI, or 8mg).")
@click.option("--gyro-noise", help="Gyro noise, 1-sigma per sample (SI, or 0.05dps).")
@click.option("--rate", type=float, help="Sample rate, Hz (default: the plan's).")
@click.option("--truth", "truth_path", type=click.Path(dir_okay=False),
              help="Predict at this truth model (default: a neutral unit).")
@click.option("--method", type=click.Choice(plan_method_names()), default="auto",
              show_default=True)
@plan_options
@click.option("--json", "as_json", is_flag=True, help="Print the result as JSON.")
def plan_optimize_cmd(plan, targets, max_duration, out, like, accel_noise, gyro_noise, rate,
                      truth_path, method, as_json, **method_options):
    """The shortest plan of PLAN's family (generated plans: number of positions
    and durations; other plans: durations only) whose predicted sigma meets
    every --target."""
    import tomllib

    from calib_cli import design
    from calib_cli.io.plan import load_plan
    from calib_cli.io.truth import load_truth
    from calib_cli.plan import plan_layout
    from calib_cli.sim import plan_make as pm

    try:
        tg = [design.parse_target(t) for t in targets]
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="--target") from None
    if out:
        from pathlib import Path

        if Path(out).resolve() == Path(plan).resolve():
            raise click.UsageError("--out must not be the input plan")
    p = load_plan(plan)
    topts = plan_option_values(design.resolve_method(p, method), method_options)
    truth = load_truth(truth_path, plan_layout(p)) if truth_path else None
    nz = _noise(p, like, accel_noise, gyro_noise, rate, truth)
    from calib_cli.cli.progress import bar

    with bar("plan optimize"):
        opt = design.optimize(p, tomllib.loads(p.text), tg, method, nz, truth, max_duration,
                              topts or None)
    sheet = design.operator_sheet(opt.plan)
    res = opt.prediction.result
    achieved = {t.text: design.target_sigmas(res, t).max() for t in tg}
    if out:
        from calib_cli.io.h5 import atomic_path

        text = pm.to_toml(opt.plan_dict, header=f"optimized by: calib plan optimize "
                                                 f"{' '.join('--target ' + t for t in targets)}")
        with atomic_path(out) as tmp:
            with open(tmp, "w", encoding="utf-8") as fh:
                fh.write(text)
    if as_json:
        print_json({"method": opt.prediction.method, "member": opt.member,
                    "targets": {t.text: t.sigma for t in tg}, "achieved": achieved,
                    "sigma": res.sigma, "unobservable": opt.prediction.unobservable,
                    "duration_s": opt.duration_after, "duration_before_s": opt.duration_before,
                    "time_saved_s": opt.duration_before - opt.duration_after,
                    "operator_sheet": sheet, "out": out})
        return
    from rich.table import Table

    for t in tg:
        info(f"{t.text}: predicted {achieved[t.text]:.3g} (worst entry)")
    saved = opt.duration_before - opt.duration_after
    info(f"{opt.member}: {opt.duration_after:.0f} s recorded (was {opt.duration_before:.0f} s; "
         f"{'saves' if saved >= 0 else 'adds'} {abs(saved):.0f} s)")
    tab = Table(title="operator sheet")
    for c in ("step", "label", "what", "attitude (roll, pitch, yaw) deg", "duration s"):
        tab.add_column(c)
    for r in sheet:
        what = r.get("turn") or ("position" if r["kind"] == "static" else r["kind"])
        tab.add_row(str(r["step"]), r["label"], what, str(r.get("attitude_deg", "-")),
                    f"{r['duration_s']:g}" if r.get("duration_s") else "-")
    err_console.print(tab)
    if out:
        info(f"-> {out}")
