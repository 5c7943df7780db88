"""A model is a list of effects; its forward function turns kinematics into
sensor outputs. The same ``predict`` serves the simulator, every estimator's
residuals and the discrepancy workflow."""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cached_property
from typing import TYPE_CHECKING

import numpy as np

from calib_cli.model.effects import (
    ADDITIVE,
    CORRECTION,
    INPUT,
    STOCHASTIC,
    TRANSFER,
    ApplyContext,
    Effect,
    Layout,
    ParamSpec,
    lag_temperature,
    make_effect,
    shift_kinematics,
)
from calib_cli.model.kinematics import Kinematics

if TYPE_CHECKING:
    from calib_cli.model.jacobian import Linearisation  # noqa: F401

SENSORS = ("accel", "gyro")


@dataclass(frozen=True)
class ImuModel:
    """An ordered set of effects acting on a unit of the given layout."""

    effects: tuple[Effect, ...]
    layout: Layout = Layout()

    # -- structure ---------------------------------------------------------
    def specs(self) -> list[ParamSpec]:
        """Parameter specs of all effects, each key once, in effect order."""
        return list(self._specs)

    @cached_property
    def _specs(self) -> tuple[ParamSpec, ...]:
        # the effects and the layout are frozen: computed once per model (the fits ask
        # for them per block)
        out, seen = [], set()
        for e in self.effects:
            for s in e.specs(self.layout):
                if s.key not in seen:
                    seen.add(s.key)
                    out.append(s)
                    if s.fixed is not None:  # shared by every caller now: read-only
                        s.fixed.setflags(write=False)
        return tuple(out)

    def spec(self, key: str) -> ParamSpec:
        for s in self.specs():
            if s.key == key:
                return s
        raise KeyError(key)

    def has(self, name: str, sensor: str | None = None) -> bool:
        return any(e.name == name and (sensor is None or e.sensor in (sensor, ""))
                   for e in self.effects)

    def find(self, name: str, sensor: str | None = None) -> Effect | None:
        for e in self.effects:
            if e.name == name and (sensor is None or e.sensor in (sensor, "")):
                return e
        return None

    def with_effect(self, effect: Effect) -> "ImuModel":
        return replace(self, effects=self.effects + (effect,))

    def without(self, name: str, sensor: str | None = None) -> "ImuModel":
        keep = tuple(e for e in self.effects
                     if not (e.name == name and (sensor is None or e.sensor == sensor)))
        return replace(self, effects=keep)

    def neutral_params(self) -> dict[str, np.ndarray]:
        """Every parameter at its neutral value (identity K, zero elsewhere)."""
        return {s.key: s.neutral() for s in self.specs()}

    # -- forward -----------------------------------------------------------
    def predict(self, params: dict, kin: Kinematics, sensors=SENSORS) -> dict[str, np.ndarray]:
        """Deterministic sensor outputs {"accel": (N, n), "gyro": (N, n)}.

        params: parameter arrays by key (missing keys take neutral values).
        """
        return {s: ctx.y for s, ctx in self.forward(params, kin, sensors).items()}

    def forward(self, params: dict, kin: Kinematics, sensors=SENSORS) -> dict[str, ApplyContext]:
        """The forward pass of ``predict``, each sensor's working state kept
        (``ApplyContext``: input vectors F, inputs u, transfer output, output y):
        ``jacobian`` differentiates through it."""
        p = self.full_params(params)
        kin = self.shifted(p, kin)
        # the lever arm also moves the point whose specific force the gyros' D sees
        acc_ctx = None
        out = {}
        for sensor in ("accel", "gyro"):
            if sensor not in sensors and not (sensor == "accel" and "gyro" in sensors):
                continue
            ctx = ApplyContext(kin, self.layout, sensor)
            if sensor == "gyro" and acc_ctx is not None:
                ctx.f_ref = acc_ctx.f_ref
            mine = [e for e in self.effects if e.sensor == sensor]
            for e in sorted((e for e in mine if e.stage == INPUT), key=lambda e: e.name):
                e.apply(p, ctx)
            transfer = [e for e in mine if e.stage == TRANSFER]
            nominal = self.layout.axes()
            ctx.u = np.einsum("ij,nij->ni", nominal, ctx.F)
            ctx.y = ctx.u.copy()
            for e in transfer:
                e.apply(p, ctx)
            ctx.y_transfer = ctx.y.copy()
            for stage in (CORRECTION, ADDITIVE):
                for e in mine:
                    if e.stage == stage:
                        e.apply(p, ctx)
            if sensor == "accel":
                acc_ctx = ctx
            if sensor in sensors:
                out[sensor] = ctx
        return out

    def full_params(self, params: dict) -> dict[str, np.ndarray]:
        """Every parameter of the model: ``params`` over the neutral values."""
        p = self.neutral_params()
        p.update({k: np.asarray(v, dtype=float) for k, v in params.items()})
        return p

    def shifted(self, p: dict, kin: Kinematics) -> Kinematics:
        """The kinematics the sensors see after the SHIFT effects (time offset, thermal lag)."""
        if self.has("time_offset"):
            kin = shift_kinematics(kin, float(p["time_offset"]))
        if self.has("thermal_lag") and kin.temp is not None:
            kin = kin.with_(temp=lag_temperature(kin.t, kin.temp, float(p["thermal_lag_tau"])))
        return kin

    def jacobian(self, params: dict, kin: Kinematics, sensor: str, columns=(),
                 inputs=()) -> "Linearisation":
        """The prediction of one sensor and its derivatives (model/jacobian.py): by the
        parameter entries ``columns`` [(key, flat index)] and by the kinematics
        ``inputs`` ("f", "w", "dw", "cen")."""
        from calib_cli.model.jacobian import linearise

        return linearise(self, params, kin, sensor, columns, inputs)

    def realise_noise(self, params: dict, kin: Kinematics, rng) -> dict[str, np.ndarray]:
        """Random realisations of the stochastic effects (bias random walk,
        flicker, white noise) over a whole record, per sensor; zeros where the
        model has none. Seeded from ``rng``; ``noise_realisation`` streams."""
        dt = float(np.median(np.diff(kin.t))) if len(kin) > 1 else 1.0
        return self.noise_realisation(params, 1.0 / dt, int(rng.integers(2**62))).next(kin)

    def noise_realisation(self, params: dict, fs: float, seed: int) -> "NoiseRealisation":
        """The stateful realisation of every stochastic effect at sample rate ``fs``:
        ``next(kin)`` gives the next chunk {"accel": (N, n), "gyro": (N, n)}. The numbers
        depend on ``seed`` and the sample index only, so the simulator (one call) and
        the emulator (chunks) draw the same stream."""
        return NoiseRealisation(self, params, fs, seed)

    def random_params(self, rng, typical: dict | None = None, skip=()) -> dict[str, np.ndarray]:
        """A random unit: each free entry neutral + N(0, typical^2), the catalogue's
        typical size unless ``typical[key]`` is given; keys in ``skip`` are not drawn.
        One draw of spec.shape per parameter, in spec order."""
        params = {}
        for spec in self.specs():
            if spec.key in skip:
                continue
            size = spec.typical if typical is None or spec.key not in typical else typical[spec.key]
            free = ~spec.fixed_mask()
            params[spec.key] = spec.neutral() + rng.standard_normal(spec.shape) * size * free
        return params


class NoiseRealisation:
    """The running noise of a model (ImuModel.noise_realisation)."""

    def __init__(self, model: ImuModel, params: dict, fs: float, seed: int):
        p = model.neutral_params()
        p.update({k: np.asarray(v, dtype=float) for k, v in params.items()})
        self.n = model.layout.n
        self.parts = [(e.sensor, e.realisation(p, model.layout, fs, seed))
                      for e in model.effects if e.stage == STOCHASTIC]

    def next(self, kin: Kinematics) -> dict[str, np.ndarray]:
        out = {s: np.zeros((len(kin), self.n)) for s in SENSORS}
        for sensor, r in self.parts:
            if r is not None:
                out[sensor] = out[sensor] + r.next(kin)
        return out


def base_model(kind: str = "triad", accel_structure: str = "full", gyro: bool = True,
               layout: Layout = Layout(), g_sensitivity: bool = False) -> ImuModel:
    """The usual starting models: bias + K (triad) or bias + installation (RIMU)."""
    effects: list[Effect] = []
    sensors = ("accel", "gyro") if gyro else ("accel",)
    for s in sensors:
        effects.append(make_effect("bias", s))
        if layout.redundant:
            effects.append(make_effect("installation", s))
        else:
            effects.append(make_effect("scale_misalignment", s,
                                       structure=accel_structure if s == "accel" else "full"))
    if g_sensitivity:
        effects.append(make_effect("g_sensitivity"))
    return ImuModel(tuple(effects), layout)


# -- parameter vectors ------------------------------------------------------


@dataclass(frozen=True)
class Packing:
    """Maps named parameter arrays onto the free-parameter vector of an estimator.

    Entries fixed by convention (spec.fixed) or by the caller (``fixed_keys``)
    are not in the vector; they keep the values of ``base``.
    """

    specs: tuple[ParamSpec, ...]
    masks: tuple[np.ndarray, ...]

    @classmethod
    def for_model(cls, model: ImuModel, keys=None, fixed_keys=()) -> "Packing":
        specs, masks = [], []
        for s in model.specs():
            if (keys is not None and s.key not in keys) or s.key in fixed_keys:
                continue
            specs.append(s)
            masks.append(~s.fixed_mask())
        return cls(tuple(specs), tuple(masks))

    @property
    def size(self) -> int:
        return int(sum(m.sum() for m in self.masks))

    def pack(self, params: dict) -> np.ndarray:
        return np.concatenate([np.asarray(params[s.key], dtype=float)[m].ravel()
                               for s, m in zip(self.specs, self.masks)] or [np.zeros(0)])

    def unpack(self, theta, base: dict) -> dict:
        out = dict(base)
        i = 0
        for s, m in zip(self.specs, self.masks):
            k = int(m.sum())
            arr = np.array(base.get(s.key, s.neutral()), dtype=float).reshape(s.shape)
            arr[m] = theta[i:i + k]
            out[s.key] = arr
            i += k
        return out

    def scales(self) -> np.ndarray:
        """Typical size of each free entry (optimiser scaling, priors)."""
        return np.concatenate([np.full(int(m.sum()), s.typical)
                               for s, m in zip(self.specs, self.masks)] or [np.zeros(0)])

    def labels(self) -> list[tuple[str, int]]:
        """[(key, flat index)] of each free entry: the covariance order of the contract."""
        out = []
        for s, m in zip(self.specs, self.masks):
            out += [(s.key, int(i)) for i in np.flatnonzero(m.ravel())]
        return out

    def sigma_arrays(self, cov_diag: np.ndarray) -> dict[str, np.ndarray]:
        """Per-key sigma arrays: sqrt of the variances for free entries, 0 for
        fixed ones, NaN where the variance is NaN (unobservable)."""
        out, i = {}, 0
        for s, m in zip(self.specs, self.masks):
            k = int(m.sum())
            arr = np.zeros(s.shape)
            arr[m] = np.sqrt(np.abs(cov_diag[i:i + k])) * np.where(np.isnan(cov_diag[i:i + k]),
                                                                  np.nan, 1.0)
            out[s.key] = arr
            i += k
        return out
