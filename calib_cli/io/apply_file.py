"""Apply a calibration file to a recording file, chunk by chunk (``calib apply``,
the batch's apply step and ``calib_cli.api.apply_file``): memory stays flat for
long recordings. The corrections themselves are ``methods/apply.py``."""

from __future__ import annotations

import numpy as np

from calib_cli.errors import InputError
from calib_cli.io.h5 import (
    attr_str,
    check_raw_header,
    open_checked,
    read_calibration,
    read_segments,
    write_provenance,
    write_segments,
    write_site_layout,
)
from calib_cli.io.h5file import h5_output, put, set_text
from calib_cli.methods.apply import (
    apply_redundant,
    apply_triad,
    check_temperature,
    check_units,
    corrected_channels,
    effective_temperature,
    is_thermal,
    proof_mass_offsets,
    redundant_extra,
)
from calib_cli.methods.rimu import apply_rimu

CHUNK = 262144  # samples per chunk: memory stays flat for long recordings


def apply_file(cal, raw, out, temp_c: float | None = None, extrapolate: bool = False,
               progress=None):
    """Correct RAW with CAL into OUT (written atomically); returns (samples, channels).
    Bad input raises InputError naming the file (exit 3). ``progress(done, total)``:
    optional, called after each chunk."""
    from calib_cli.io import validate

    c = read_calibration(cal)
    validate.check_calibration(c, cal)
    rimu = c.layout.redundant
    # a redundant unit's model with catalogue effects beyond bias and installation
    # (fit rimu --with): inverted numerically through the forward model
    rimu_extra = rimu and redundant_extra(c)
    with open_checked(raw, ("raw",)) as src:
        if "samples" not in src:
            raise InputError("missing group /samples (a recording is expected here)", raw)
        n, units, site, layout = check_raw_header(src, raw)
        smp = src["samples"]
        time = validate.load(smp["time"], raw)
        validate.check_time(time, raw)
        validate.check_rate(time, raw)
        segments = read_segments(src, raw, n)
        check_units(c, units, raw)
        chans = corrected_channels(c)
        n = smp["time"].shape[0]
        temp_eff = None
        if is_thermal(c):
            if "temp" in smp:
                temp_in = np.asarray(validate.load(smp["temp"], raw), dtype=float)
            elif temp_c is not None:
                temp_in = np.full(n, float(temp_c))
            else:
                raise InputError("the calibration has temperature terms but the recording has "
                                 "no temperature column (give --temp DEGC)", raw)
            check_temperature(c, temp_in, raw, extrapolate)
            temp_eff = effective_temperature(c, time, temp_in)
        with h5_output(out) as dst:
            write_provenance(dst, "corrected", [cal, raw], c.serial or (
                attr_str(src, "unit_serial") or None),
                {"plan_kind": attr_str(src, "plan_kind", "static"),
                 "corrected_channels": ",".join(chans)})
            # through the checked readers, not copied: a damaged input is not passed on
            write_segments(dst, segments)
            write_site_layout(dst, site, layout)
            if "plan" in src:
                set_text(dst.create_group("plan"), "text", attr_str(src["plan"], "text"))
            out_s = dst.create_group("samples")
            put(out_s, "time", time)
            for k in ("temp", "table_angle", "table_rate"):
                if k in smp:
                    put(out_s, k, validate.load(smp[k], raw))
            if "sample_kind" in smp.attrs:
                set_text(out_s, "sample_kind", attr_str(smp, "sample_kind"))
            acc = out_s.create_dataset("accel", shape=smp["accel"].shape, dtype="f8", fletcher32=True,
                                       chunks=True)
            gyr = (out_s.create_dataset("gyro", shape=smp["gyro"].shape, dtype="f8", chunks=True,
                                       fletcher32=True)
                   if "gyro" in smp else None)
            body = {}
            if smp["accel"].shape[1] != c.layout.n:
                raise InputError(f"the recording has {smp['accel'].shape[1]} channels per "
                                 f"sensor, the calibration {c.layout.n}", raw)
            if rimu:  # a redundant unit also gets the body-frame estimate (docs/rimu.md)
                for s in chans:
                    if s in smp:
                        body[s] = out_s.create_dataset(f"{s}_body", shape=(n, 3), dtype="f8", fletcher32=True,
                                                       chunks=True)
            size = proof_mass_offsets(c) is not None and gyr is not None and not rimu
            for a in range(0, n, CHUNK):
                if progress is not None:
                    progress(a // CHUNK, -(-n // CHUNK))
                b = min(n, a + CHUNK)
                a0, b0 = (max(0, a - 1), min(n, b + 1)) if size else (a, b)
                a_in = np.asarray(validate.rows(smp["accel"], a0, b0, raw), dtype=float)
                g_in = (np.asarray(validate.rows(smp["gyro"], a0, b0, raw), dtype=float)
                        if gyr is not None else None)
                validate.check_finite(a_in, raw, "/samples/accel", a0)
                validate.check_magnitudes(a_in, "accel", units["accel"], raw, a0)
                if g_in is not None:
                    validate.check_finite(g_in, raw, "/samples/gyro", a0)
                    validate.check_magnitudes(g_in, "gyro", units["gyro"], raw, a0)
                if size:  # one sample of context each side for the rate derivative
                    f, w = apply_triad(c, a_in, g_in, accel_si=units["accel"] != "count",
                                       temp=None if temp_eff is None else temp_eff[a0:b0],
                                       time=time[a0:b0])
                    f, w = f[a - a0:a - a0 + b - a], w[a - a0:a - a0 + b - a]
                elif rimu:
                    res = (apply_redundant(c, a_in, g_in,
                                           temp=None if temp_eff is None else temp_eff[a:b])
                           if rimu_extra else apply_rimu(c, a_in, g_in))
                    f, w = res["accel"], res["gyro"]
                    for s, ds in body.items():
                        ds[a:b] = res[f"{s}_body"]
                else:
                    f, w = apply_triad(c, a_in, g_in, accel_si=units["accel"] != "count",
                                       temp=None if temp_eff is None else temp_eff[a:b])
                acc[a:b] = f
                if gyr is not None:
                    gyr[a:b] = w
            set_text(out_s, "accel_units", "m/s^2" if "accel" in chans else units["accel"])
            set_text(out_s, "gyro_units", "rad/s" if "gyro" in chans else units["gyro"])
    return n, chans
