"""What a turntable plan will deliver (``calib plan check``, calib_cli/design.py): the fit's
own rows and noise model on a noise-free record of the plan, the noise levels given.

The record is simulated at a known unit without noise; the fit runs on it with every
noise level held (the sensors' white noise, the table axis's, the angle channel's and
the rate channel's), so it stops at the truth with zero residuals and its covariance is
the inverse information of the same rows, priors and holds as the fit on a real record.
The levels come from ``--like RAW``: the fit of RAW itself (what it estimated, and which
channels it used, cycle by cycle); without it, from the stated sensor noise with the table
at its best (the axis at the fit's floor, the channels at their reading resolution).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from calib_cli.data import CalibrationResult, Recording
from calib_cli.methods.turntable import estimator as es
from calib_cli.methods.turntable.fit import prepared, solved
from calib_cli.methods.turntable.options import TurntableOptions
from calib_cli.methods.turntable.result import build


@dataclass(frozen=True)
class Levels:
    """The noise levels of a fit (SI, per sample or per block as the rows take them)."""

    accel: np.ndarray  # (3,) m/s^2 per sample
    gyro: np.ndarray  # (3,) rad/s per sample
    axis: float  # rad per block: the table axis
    angle: float | None = None  # rad: the angle channel's rows' sigma
    angle_white: float | None = None  # rad: its white noise (the shape check's floor)
    rate: float | None = None  # rad/s per sample: the rate channel's own noise
    rate_row: float | None = None  # rad: the rate channel's rows' sigma
    inflation: float = 1.0
    mode: str = "off"  # the channels the fit used
    angle_cycles: tuple = ()  # per cycle: the angle channel used
    rate_cycles: tuple = ()


_FITS: list = []  # the last fits of --like recordings: (recording, options, (pb, st))


def _like_fit(rec: Recording, opt: TurntableOptions) -> tuple:
    """(problem, state) of the fit of ``rec``, run once per recording and options (the
    levels and the lever arms come from the same fit)."""
    for r, o, out in _FITS:
        if r is rec and o == opt:
            return out
    pb, st, _, _ = solved(rec, opt)
    _FITS[:] = _FITS[-3:] + [(rec, opt, (pb, st))]
    return pb, st


def lever_arms_like(plan, like: Recording, opt: TurntableOptions):
    """The plan with each rotating segment's lever arm (``lever_arm_m``, the unit the
    prediction is simulated at and the fit's prior mean) as the fit of ``like`` estimates
    it: the centripetal and tangential terms carry the information that separates the
    gyros' biases from their g-sensitivity and the accelerometers' terms, in proportion
    to the lever arms (on a vertical axis, predicted at the plan's own lever arms, half
    the sigma the fit delivered). Segments the fit does not estimate keep the plan's."""
    pb, st = _like_fit(like, opt)
    if not pb.pm.has("lever_arm"):
        return plan
    by_plan = {}
    for cy in pb.cycles:
        if not cy.static:
            # the lever arm per unit of the gyros' rate squared (the centripetal term the
            # accelerometers see), which the prediction's unit (K = I) reproduces; the
            # lever arm itself is that times the gyro scale about the axis squared, which
            # on a vertical axis without channels nothing determines (1.5 at the fit's end)
            u = cy.basis @ st.theta[pb.pm.idx["lever_arm"][cy.model_index]]
            by_plan.setdefault(like.segments[cy.seg_index].plan_index, u)
    segs = list(plan.segments)
    for i, seg in enumerate(segs):
        if seg.kind == "rotating" and i in by_plan:
            segs[i] = replace(seg, lever_arm=by_plan[i].copy())
    return replace(plan, segments=tuple(segs))


def levels_of(rec: Recording, opt: TurntableOptions) -> Levels:
    """The levels the fit estimates on ``rec`` (the recording --like names)."""
    pb, st = _like_fit(rec, opt)
    return Levels(pb.sig_a.copy(), pb.sig_g.copy(), float(np.sqrt(st.axis_var)),
                  pb.sig_enc if pb.enc is not None else None,
                  pb.sig_enc_floor if pb.enc is not None else None,
                  pb.sig_rate if pb.rate is not None else None,
                  pb.sig_rate_row if pb.rate is not None else None,
                  float(st.inflation), _mode(pb),
                  tuple(e is not None for e in pb.enc) if pb.enc is not None else (),
                  tuple(r is not None for r in pb.rate) if pb.rate is not None else ())


def _mode(pb) -> str:
    if pb.enc is not None:
        return "both" if pb.rate is not None else "angle"
    return "rate" if pb.rate is not None else "off"


def covariance_at(rec: Recording, opt: TurntableOptions, noise: dict,
                  like: Recording | None = None, per_cycle: bool = True) -> CalibrationResult:
    """The fit's covariance on the noise-free record ``rec`` of a plan. noise: {"accel":
    (3,), "gyro": (3,)} per-sample sigma (SI); like: a recording whose fit gives the
    table's levels and channels (else the table at its best); per_cycle: ``like`` was
    recorded from this plan, so its channels are taken cycle by cycle (else only which
    channels its fit used)."""
    from calib_cli.methods.blas_threads import one_blas_thread

    with one_blas_thread():
        return _covariance_at(rec, opt, noise, like, per_cycle)


def _covariance_at(rec, opt, noise, like, per_cycle=True) -> CalibrationResult:
    lv = levels_of(like, opt) if like is not None else None
    if lv is not None and per_cycle:
        rec = _channels_as(rec, lv)
        sig = {"accel": lv.accel, "gyro": lv.gyro}
        mode = lv.mode if opt.table_encoder in ("auto", lv.mode) else opt.table_encoder
    else:
        sig = {k: np.asarray(noise[k], float) * np.ones(3) for k in ("accel", "gyro")}
        mode = opt.table_encoder
    q = replace(opt, noise=sig, table_encoder=mode,
                axis_sigma=opt.axis_sigma if opt.axis_sigma is not None else
                (lv.axis if lv is not None else None))
    pb, st = prepared(rec, q)
    pb.fixed_levels = True
    floor = es.axis_floor(pb.sig_g, pb.block_n, rec.sample_rate)
    if q.axis_sigma is None:
        st.axis_var = floor ** 2
    if pb.enc is not None:
        pb.sig_enc = opt.encoder_sigma or (lv.angle if lv is not None and lv.angle else
                                           max(pb.sig_enc_floor, 1e-9))
        pb.sig_enc_floor = lv.angle_white if lv is not None and lv.angle_white else pb.sig_enc
    if pb.rate is not None:
        if lv is not None and lv.rate is not None:
            pb.sig_rate, pb.sig_rate_row = lv.rate, lv.rate_row
        else:
            from calib_cli.methods.turntable.setup import RATE_ANGLE_FLOOR

            pb.sig_rate_row = RATE_ANGLE_FLOOR
    if lv is not None:
        st.inflation = lv.inflation
    out = build(*solved(rec, q, start=(pb, st)))
    out.stats["prediction_levels"] = {
        "table_axis_noise_mrad": float(np.sqrt(st.axis_var) * 1e3),
        "angle_sigma_urad": None if pb.enc is None else pb.sig_enc * 1e6,
        "rate_row_sigma_urad": None if pb.rate is None else pb.sig_rate_row * 1e6,
        "source": "like" if lv is not None else "stated"}
    return out


def _channels_as(rec: Recording, lv: Levels) -> Recording:
    """The noise-free record with the table channels the fit of --like did not use blanked,
    cycle by cycle (the cycles in the fit's order: the same plan)."""
    from calib_cli.methods.turntable.setup import select_cycles

    cycles = [cy for cy in select_cycles(rec, TurntableOptions()) if not cy.static]
    ang = None if rec.table_angle is None or lv.mode in ("off", "rate") else \
        np.array(rec.table_angle, float)
    rt = None if rec.table_rate is None or lv.mode in ("off", "angle") else \
        np.array(rec.table_rate, float)
    for c, cy in enumerate(cycles):
        if ang is not None and c < len(lv.angle_cycles) and not lv.angle_cycles[c]:
            ang[cy.sl] = np.nan
        if rt is not None and c < len(lv.rate_cycles) and not lv.rate_cycles[c]:
            rt[cy.sl] = np.nan
    return rec.with_(table_angle=ang, table_rate=rt)
