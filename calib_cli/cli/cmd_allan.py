"""calib allan RAW [--segment LABEL] [--out ALLAN.h5] [--plot FILE.png] [--json]

Overlapping Allan deviation of every channel, read chunk by chunk (memory
does not grow with the recording), and the IEEE Std 952 noise terms.
"""

from __future__ import annotations

import click
import numpy as np
from rich.table import Table

from calib_cli.cli.common import Ctx, info, out_console, print_json
from calib_cli.cli.main import cli
from calib_cli.errors import EstimationError, InputError
from calib_cli.io.h5 import atomic_path, attr_str, check_raw_header, open_checked, read_segments
from calib_cli.methods import allan as A

COMPLETE_COMMAND = True  # every subcommand lives here: loaded alone (cli/main.py)

CHUNK = 1 << 18  # samples per read
DEFAULT_TARGET = {"m/s^2": 1e-4, "rad/s": 1e-5}  # ~10 ug, ~2 deg/h

# terminal display: term -> unit -> (factor, shown unit)
_DPS = 180 / np.pi
DISPLAY = {
    ("quantization", "rad/s"): (_DPS * 3600, "arcsec"),
    ("quantization", "m/s^2"): (1e3, "mm/s"),
    ("random_walk", "rad/s"): (_DPS * 60, "deg/sqrt(h)"),
    ("bias_instability", "rad/s"): (_DPS * 3600, "deg/h"),
    ("rate_random_walk", "rad/s"): (_DPS * 3600 * 60, "deg/h/sqrt(h)"),
    ("random_walk", "m/s^2"): (60.0, "m/s/sqrt(h)"),
    ("bias_instability", "m/s^2"): (1e6 / 9.80665, "ug"),
    ("rate_random_walk", "m/s^2"): (1e6 / 9.80665 * 60, "ug/sqrt(h)"),
}


def channel_names(prefix: str, n: int) -> list[str]:
    return [f"{prefix}_{'xyz'[i]}" for i in range(3)] if n == 3 else [
        f"{prefix}_{i}" for i in range(n)]


def _span(h5, path, segment, hint="--segment"):
    """(start, stop, label) of the samples to analyse; ``hint``: how the user names a
    segment (`calib report` has no --segment: it points to `calib allan`)."""
    n = h5["samples"]["time"].shape[0]
    segs = read_segments(h5, path) if "segments" in h5 else ()
    if segment is not None:
        for s in segs:
            if s.label == segment:
                return s.start, s.stop, s.label
        raise InputError(f"no segment labelled {segment!r} (segments: "
                         f"{', '.join(s.label for s in segs) or 'none'})", path)
    if not segs:
        return 0, n, "(whole record)"
    statics = [s for s in segs if s.kind == "static"]
    if not statics:
        raise EstimationError("the record has no static segment (the Allan deviation needs "
                              "the unit at rest); name a segment with " + hint, path)
    best = max(statics, key=lambda s: s.n)
    if len(segs) > 1:
        info(f"{path}: {len(segs)} segments; using the longest static one, {best.label!r} "
             f"(choose with {hint})")
    return best.start, best.stop, best.label


def _parse_targets(targets, units_by_sensor, path):
    out = {s: DEFAULT_TARGET.get(u, np.nan) for s, u in units_by_sensor.items()}
    for t in targets:
        if "=" not in t:
            raise click.BadParameter(f"{t!r}: expected SENSOR=VALUE, e.g. gyro=1e-5",
                                     param_hint="--target")
        k, v = t.split("=", 1)
        if k not in out:
            raise click.BadParameter(f"{k!r}: the file has {', '.join(out)}",
                                     param_hint="--target")
        try:
            out[k] = float(v)
        except ValueError:
            raise click.BadParameter(f"{v!r} is not a number", param_hint="--target") from None
    return out


def compute_allan(raw, segment=None, targets=(), stride_div=A.STRIDE_DIV,
                  hint="--segment") -> A.AllanResult:
    """Read RAW chunk-wise and run the Allan analysis (used by `allan` and `report`)."""
    with open_checked(raw, ("raw", "corrected")) as h5:
        if "samples" not in h5 or "time" not in h5["samples"]:
            raise InputError("missing field /samples/time", raw)
        smp = h5["samples"]
        from calib_cli.io import validate

        units = check_raw_header(h5, raw)[1]  # issues 15, 37: types, shapes, site before use
        start, stop, label = _span(h5, raw, segment, hint)
        n = stop - start
        sensors = [s for s in ("accel", "gyro") if s in smp]
        units = {s: units[s] for s in sensors}
        tgt = _parse_targets(targets, units, raw)
        if n < 2 * A.MIN_CLUSTERS + 1:
            raise EstimationError(f"segment {label!r} has {n} samples; an Allan "
                                  "deviation needs a free-running record (minutes to hours)",
                                  raw)
        t_head = validate.rows(smp["time"], start, min(stop, start + 4096), raw)
        tau0 = float(np.median(np.diff(t_head)))
        if not tau0 > 0:
            raise InputError("time does not increase", raw)
        channels, chan_units, chan_tgt = [], [], []
        for s in sensors:
            m = smp[s].shape[1]
            channels += channel_names(s, m)
            chan_units += [units[s]] * m
            chan_tgt += [tgt[s]] * m

        def chunks():
            for a in range(start, stop, CHUNK):
                b = min(stop, a + CHUNK)
                tt = validate.rows(smp["time"], max(a - 1, start), b, raw)
                dt = np.diff(tt)
                bad = np.flatnonzero(np.abs(dt - tau0) > 0.5 * tau0)
                if len(bad):
                    raise InputError(f"irregular sampling at t = {tt[bad[0]]:.6g} s (step "
                                     f"{dt[bad[0]]:.3g} s, nominal {tau0:.3g} s): the Allan "
                                     "deviation needs an evenly sampled record without gaps", raw)
                parts = [np.asarray(validate.rows(smp[s], a, b, raw), dtype=float)
                         for s in sensors]
                for s, x in zip(sensors, parts):  # issue 37: 1e300 in a cell is no sample
                    validate.check_finite(x, raw, f"/samples/{s}", a)
                    validate.check_magnitudes(x, s, units[s], raw, a)
                block = np.column_stack(parts)
                yield block

        from calib_cli.cli.progress import track

        feed = track(chunks(), "Allan deviation", -(-n // CHUNK))  # a bar on a terminal
        return A.allan_of_chunks(feed, n, tau0, channels, chan_units, chan_tgt, stride_div,
                                 meta={"source_kind": attr_str(h5, "kind"), "segment": label,
                                       "start": int(start), "stop": int(stop),
                                       "serial": attr_str(h5, "unit_serial") or None})


def allan_json(res: A.AllanResult) -> dict:
    chans = {}
    for i, c in enumerate(res.channels):
        chans[c] = {"unit": res.units[i],
                    **{k: {f: res.terms[k][f][i] for f in ("value", "lo", "hi", "tau")}
                       for k in res.terms},
                    "tau_min": res.tau_min[i], "averaging_target": res.target[i],
                    "averaging_time": res.averaging_time[i],
                    "min_averaging_time": res.min_avg()[i]}
    return {"kind": "allan", "segment": res.meta.get("segment"), "tau0": res.tau0,
            "samples": res.n_samples, "duration_s": res.duration,
            "confidence": A.CONFIDENCE, "term_units": {u: A.term_units(u) for u in
                                                       sorted(set(res.units))},
            "channels": chans,
            "curve": {"tau": res.tau, "clusters": res.clusters,
                      "adev": {c: res.adev[:, i] for i, c in enumerate(res.channels)}}}


def _fmt(term, unit, v, lo, hi):
    if not np.isfinite(v):
        return "not visible"
    f, u = DISPLAY.get((term, unit), (1.0, A.term_units(unit)[term]))
    return f"{v * f:.3g} [{lo * f:.3g}, {hi * f:.3g}] {u}"


def render_allan(res: A.AllanResult, title: str) -> None:
    t = Table(title=f"{title}: {res.n_samples} samples, {res.duration:.6g} s "
              f"(tau0 {res.tau0:.3g} s); values [{A.CONFIDENCE:.0%} interval]")
    for col in ("channel", "quantization Q", "random walk N", "bias instability B",
                "rate random walk K", "tau at minimum", "averaging time", "min. averaging (Q)"):
        t.add_column(col)
    for i, c in enumerate(res.channels):
        u = res.units[i]
        row = [_fmt(k, u, *(res.terms[k][f][i] for f in ("value", "lo", "hi")))
               for k in A.TERM_NAMES]
        at = res.averaging_time[i]
        if not np.isfinite(res.target[i]):
            avg = "no target (--target)"
        else:
            avg = (f"{at:.3g} s" if np.isfinite(at) else "target not reached") + \
                f" (target {res.target[i]:.3g} {u})"
        tq = res.min_avg()[i]
        t.add_row(c, *row, f"{res.tau_min[i]:.3g} s", avg,
                  f"{tq:.3g} s" if np.isfinite(tq) else "-")
    out_console.print(t)


def show_allan(files, as_json, covariance):
    from calib_cli.io.allan_h5 import read_allan

    res = read_allan(files[0])
    if as_json:
        print_json(allan_json(res))
    else:
        render_allan(res, files[0])
    return 0


@cli.command("allan")
@click.argument("raw", type=click.Path(dir_okay=False))
@click.option("--segment", help="Label of the segment to analyse (default: the longest "
              "static segment; the whole record when it has no segments).")
@click.option("--out", type=click.Path(dir_okay=False), help="Write an 'allan' HDF5 file.")
@click.option("--plot", type=click.Path(dir_okay=False), help="Write the Allan plot (PNG).")
@click.option("--target", "targets", multiple=True, metavar="SENSOR=VALUE",
              help="Noise target for the averaging time, in the data's unit, e.g. "
              "gyro=1e-5 (rad/s); default accel=1e-4 m/s^2, gyro=1e-5 rad/s.")
@click.option("--exact", is_flag=True, help="Use every overlapping cluster at every tau "
              "(slower; the default keeps 16 per cluster length).")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
@click.option("--kalibr", "kalibr_path", type=click.Path(dir_okay=False),
              help="Write Kalibr's imu.yaml (noise densities and random walks; docs/allan.md).")
@click.option("--rostopic", default="/imu0", show_default=True,
              help="--kalibr: the IMU topic written into imu.yaml.")
def allan_cmd(raw, segment, out, plot, targets, exact, as_json, kalibr_path, rostopic):
    """Allan deviation and noise terms (IEEE Std 952) of a free-running record."""
    res = compute_allan(raw, segment, targets, 0 if exact else A.STRIDE_DIV)
    if kalibr_path:
        from calib_cli.io.export_autopilot import kalibr_from_allan, kalibr_yaml

        d = kalibr_from_allan(res, rostopic)
        text = kalibr_yaml(d)
        with atomic_path(kalibr_path) as tmp, open(tmp, "w", encoding="utf-8") as fh:
            fh.write(text)
        missing = [k for k, v in d.items() if v is None]
        if missing:
            info(f"warning: {', '.join(missing)} not visible in this record (null in "
                 f"{kalibr_path}): record longer")
    if out:
        from calib_cli.io.allan_h5 import write_allan

        write_allan(out, res, [raw], res.meta.get("serial"))
    if plot:
        from calib_cli.report.figures import allan_figure, png_bytes

        data = png_bytes(allan_figure(res))
        with atomic_path(plot) as tmp, open(tmp, "wb") as fh:
            fh.write(data)
    if as_json:
        print_json(allan_json(res))
    elif not Ctx.quiet:
        render_allan(res, f"{raw} [{res.meta.get('segment')}]")
    for p in (out, plot, kalibr_path):
        if p:
            info(f"-> {p}")
    return 0


def _register_show():
    from calib_cli.cli.cmd_show import SHOWERS

    SHOWERS["allan"] = show_allan


_register_show()
