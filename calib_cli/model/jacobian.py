"""The linearised measurement model: a sensor's prediction and its derivatives by
parameter entries and by the kinematics, from the effects' own derivatives.

The forward pass of one sensor (``ImuModel.forward``) is

    F_i = input vector of channel i (INPUT effects: lever arm, proof masses)
    y_t = transfer(F)                     (TRANSFER: K, or a RIMU installation)
    y   = y_t + corrections(u, y_t, F)    (CORRECTION: nonlinearity, asymmetry, ...)
          + additive(f_ref)               (ADDITIVE: bias, g-sensitivity)

with u_i = nominal_i . F_i. Every term after the INPUT stage depends on channel i's own
input vector F_i only, so the chain rule needs one gain per channel,
g_i = d y_i / d F_i = (1 + d corrections / d y_t) d y_t / d F_i + d corrections / d F_i,
and the derivative by an INPUT effect's parameter (or by the kinematics the INPUT effects
read: the centripetal operator, the angular acceleration) is g_i . dF_i/d(.). Effects
without derivatives of their own (a time shift, a RIMU installation) get central
differences of the forward model, which are exact for terms linear in the entry.

Estimators assemble their rows from this (methods/turntable/blocks.py); nothing here is
specific to a method.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib_cli.model.effects import ADDITIVE, CORRECTION, INPUT, SHIFT, STOCHASTIC, TRANSFER
from calib_cli.model.kinematics import Kinematics

INPUTS = ("f", "w", "dw", "cen")


@dataclass(frozen=True)
class Linearisation:
    """y (N, n): the prediction. d_params (N, n, k): by the entries ``columns`` [(key,
    flat index)]. d_inputs: by the kinematics, "f", "w", "dw" (N, n, 3) and "cen"
    (N, n, 3, 3) (the rows' centripetal operator)."""

    y: np.ndarray
    columns: tuple
    d_params: np.ndarray
    d_inputs: dict


def _owner(model, key: str):
    for e in model.effects:
        if any(s.key == key for s in e.specs(model.layout)):
            return e
    raise KeyError(f"no effect of the model has the parameter {key!r}")


def _exact(model, sensor: str) -> bool:
    """Whether the sensor's pipeline has analytic derivatives throughout (then the input
    derivatives are exact; else central differences of the forward model)."""
    involved = [e for e in model.effects if e.stage != STOCHASTIC and (
        e.sensor == sensor or (sensor == "gyro" and e.sensor == "accel" and e.stage == INPUT))]
    return all(e.has_derivatives or e.stage == SHIFT for e in involved)


def linearise(model, params: dict, kin: Kinematics, sensor: str, columns=(), inputs=()
              ) -> Linearisation:
    """``ImuModel.jacobian`` (module docstring)."""
    columns = tuple((str(k), int(f)) for k, f in columns)
    for name in inputs:
        if name not in INPUTS:
            raise ValueError(f"unknown kinematics input {name!r}; known: {', '.join(INPUTS)}")
    p = model.full_params(params)
    ctxs = model.forward(p, kin, ("accel", sensor) if sensor == "gyro" else (sensor,))
    ctx = ctxs[sensor]
    N, n = ctx.y.shape
    mine = [e for e in model.effects if e.sensor == sensor]
    g, tg = _gains(model, p, ctx, mine)
    fref_gain = np.zeros((N, n, 3))
    for e in mine:
        if e.stage == ADDITIVE and e.has_derivatives:
            d = e.d_fref(p, ctx)
            if d is not None:
                fref_gain = fref_gain + d
    d_params = np.zeros((N, n, len(columns)))
    by_key: dict = {}
    for q, (key, flat) in enumerate(columns):
        by_key.setdefault(key, []).append((q, flat))
    for key, items in by_key.items():
        qs = [q for q, _ in items]
        flats = [f for _, f in items]
        e = _owner(model, key)
        if not e.has_derivatives or e.stage == SHIFT:
            d_params[:, :, qs] = _numeric_params(model, p, kin, sensor, key, flats)
            continue
        if e.stage == INPUT:
            ectx = ctxs["accel"] if e.sensor != sensor else ctx
            dF, dref = e.d_param(p, ectx, key, flats)
            if e.sensor == sensor:
                d_params[:, :, qs] = np.einsum("nia,niaq->niq", g, dF)
            if dref is not None and np.any(fref_gain):
                d_params[:, :, qs] += np.einsum("nia,naq->niq", fref_gain, dref)
        elif e.sensor != sensor:
            continue  # the other sensor's transfer or corrections
        elif e.stage == TRANSFER:
            d_params[:, :, qs] = (1.0 + tg)[:, :, None] * e.d_param(p, ctx, key, flats)
        else:  # CORRECTION, ADDITIVE
            d_params[:, :, qs] = e.d_param(p, ctx, key, flats)
    d_inputs = {}
    if inputs:
        if _exact(model, sensor):
            d_inputs = _analytic_inputs(model, p, ctxs, sensor, g, fref_gain, inputs)
        else:
            d_inputs = _numeric_inputs(model, p, kin, sensor, inputs)
    return Linearisation(ctx.y, columns, d_params, d_inputs)


def _gains(model, p, ctx, mine) -> tuple[np.ndarray, np.ndarray]:
    """g (N, n, 3) = d y_i / d F_i and tg (N, n) = d corrections / d y_t."""
    N, n = ctx.y.shape
    tvec = None
    for e in mine:
        if e.stage == TRANSFER and e.has_derivatives:
            tvec = np.broadcast_to(e.gain(p, ctx), (N, n, 3)).astype(float)
    if tvec is None:  # no transfer effect (or one without derivatives): y_t = u = nominal . F
        tvec = np.broadcast_to(model.layout.axes(), (N, n, 3)).astype(float)
    tg = np.zeros((N, n))
    cg = np.zeros((N, n, 3))
    for e in mine:
        if e.stage == CORRECTION and e.has_derivatives:
            a = e.transfer_gain(p, ctx)
            if a is not None:
                tg = tg + a
            b = e.gain(p, ctx)
            if b is not None:
                cg = cg + b
    return (1.0 + tg)[:, :, None] * tvec + cg, tg


def _analytic_inputs(model, p, ctxs, sensor, g, fref_gain, inputs) -> dict:
    ctx = ctxs[sensor]
    N, n = ctx.y.shape
    out = {}
    input_effects = [e for e in model.effects if e.stage == INPUT and e.has_derivatives]
    for name in inputs:
        shape = (N, n, 3, 3) if name == "cen" else (N, n, 3)
        d = np.zeros(shape)
        if name == "f":
            if sensor == "accel":
                d += g  # F_i = f + (rigid terms)
            d += fref_gain  # f_ref = f + (lever-arm term)
        if name == "w" and sensor == "gyro":
            d += g  # the gyros' input vector is the rate
        for e in input_effects:
            ectx = ctxs["accel"] if e.sensor == "accel" else ctx
            if e.sensor not in (sensor, "accel"):
                continue
            dF, dref = e.d_kin(p, ectx, name)
            if dF is None:
                continue
            if e.sensor == sensor:
                if name == "cen":
                    d += np.einsum("nia,niabc->nibc", g, dF)
                else:
                    d += np.einsum("nia,niak->nik", g, dF)
            if dref is not None and np.any(fref_gain):
                if name == "cen":
                    d += np.einsum("nia,nabc->nibc", fref_gain, dref)
                else:
                    d += np.einsum("nia,nak->nik", fref_gain, dref)
        out[name] = d
    return out


def _step(spec, value: float) -> float:
    return 1e-6 * max(float(spec.typical), abs(float(value)), 1e-12)


def _numeric_params(model, p, kin, sensor, key, flats) -> np.ndarray:
    """Central differences of the forward model by entries of ``key``: (N, n, k)."""
    spec = model.spec(key)
    cols = []
    for flat in flats:
        base = np.array(p[key], dtype=float)
        h = _step(spec, base.ravel()[flat])
        up, dn = base.copy(), base.copy()
        up.ravel()[flat] += h
        dn.ravel()[flat] -= h
        y_up = model.predict({**p, key: up}, kin, (sensor,))[sensor]
        y_dn = model.predict({**p, key: dn}, kin, (sensor,))[sensor]
        cols.append((y_up - y_dn) / (2 * h))
    return np.stack(cols, axis=-1) if cols else np.zeros(kin.f.shape[:1] + (model.layout.n, 0))


def _numeric_inputs(model, p, kin, sensor, inputs) -> dict:
    """Central differences of the forward model by the kinematics inputs."""
    out = {}
    for name in inputs:
        arr = getattr(kin, name)
        if arr is None:
            continue
        arr = np.asarray(arr, float)
        comps = [(a, b) for a in range(3) for b in range(3)] if name == "cen" else range(3)
        cols = []
        for c in comps:
            h = 1e-6 * max(float(np.max(np.abs(arr))), 1.0)
            up, dn = arr.copy(), arr.copy()
            up[(slice(None),) + ((c,) if isinstance(c, int) else c)] += h
            dn[(slice(None),) + ((c,) if isinstance(c, int) else c)] -= h
            y_up = model.predict(p, kin.with_(**{name: up}), (sensor,))[sensor]
            y_dn = model.predict(p, kin.with_(**{name: dn}), (sensor,))[sensor]
            cols.append((y_up - y_dn) / (2 * h))
        d = np.stack(cols, axis=-1)
        out[name] = d.reshape(d.shape[:2] + (3, 3)) if name == "cen" else d
    return out
