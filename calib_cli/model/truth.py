"""Truth models (a unit's effects with parameter values, noise and output units) and
the serialisation of effects (``describe_effect``/``effect_from_description``,
written into every calibration file). Pure: the TOML file is read by ``io/truth.py``.

Truth TOML (docs/simulate.md):

    [params]                 # contract keys; a unit suffix converts to SI
    accel_bias_mg = [2.0, -1.5, 3.0]
    accel_K = [[1.002, 0.001, 0.0], [0.0, 0.998, 0.0], [0.0, 0.0, 1.001]]
    gyro_bias_dps = [0.2, -0.1, 0.05]
    [noise]                  # white noise, 1-sigma per sample (or *_density per sqrt(Hz))
    accel_white = 0.003      # m/s^2
    gyro_white = 0.001       # rad/s
    [output]
    units = "si"             # or "count": params then in counts, outputs rounded
    [options]
    tangential = true        # lever-arm/proof-mass tangential term

The effects in the truth model are the ones whose parameters appear.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from calib_cli.errors import InputError
from calib_cli.model.effects import CATALOGUE, Effect, Layout, make_effect
from calib_cli.model.imu_model import ImuModel
from calib_cli.units import split_suffix

DEFAULT_NOISE = {"accel_white": 3e-3, "gyro_white": 1e-3}  # m/s^2, rad/s per sample


@dataclass(frozen=True)
class Truth:
    """A truth model: effects with parameter values, noise, output units."""

    model: ImuModel
    params: dict
    noise: dict = field(default_factory=lambda: dict(DEFAULT_NOISE))
    counts: bool = False
    quantize: bool = False

    def effect_list(self) -> list[dict]:
        return [describe_effect(e) for e in self.model.effects]

    def noise_model(self) -> tuple[ImuModel, dict]:
        """The model with its white noise as effects (``white_noise`` per sensor with a
        [noise] entry) and the parameters including the noise levels: what the
        simulator and the emulator realise (``ImuModel.noise_realisation``)."""
        effects = list(self.model.effects)
        params = dict(self.params)
        for s in ("accel", "gyro"):
            keys = [k for k in (f"{s}_white", f"{s}_white_density") if k in self.noise]
            if keys and not any(e.name == "white_noise" and e.sensor == s for e in effects):
                effects.append(make_effect("white_noise", s))
            n = self.model.layout.n
            for k in keys:
                params[k] = np.broadcast_to(np.asarray(self.noise[k], dtype=float), (n,)).copy()
        return ImuModel(tuple(effects), self.model.layout), params


def describe_effect(e: Effect) -> dict:
    d = {"name": e.name, "sensor": e.sensor}
    for opt in ("structure", "tangential", "order", "temp_ref", "scale_on"):
        if hasattr(e, opt):
            d[opt] = getattr(e, opt)
    return d


def effect_from_description(d: dict) -> Effect:
    opts = {k: v for k, v in d.items() if k not in ("name", "sensor")}
    if d.get("name") == "temperature_drift" and "order" not in d:
        # written before the contract's form (section 7): the scale term was on
        # the nominal input; read the file as it was fitted (docs/thermal.md)
        opts["scale_on"] = "input"
    return make_effect(d["name"], d.get("sensor") or "accel", **opts)


def key_owner(layout: Layout, options: dict) -> dict[str, Effect]:
    """param key -> the effect instance that owns it, for this layout."""
    owners = {}
    for name in CATALOGUE:
        for sensor in ("accel", "gyro"):
            cls = CATALOGUE[name]
            if ("redundant" if layout.redundant else "triad") not in cls.layouts:
                continue
            if cls.noise_table:  # its levels are the truth file's [noise] table
                continue
            opts = {}
            if name in ("lever_arm", "proof_mass_offsets"):
                opts["tangential"] = bool(options.get("tangential", True))
            try:
                e = make_effect(name, sensor, **opts)
            except TypeError:
                continue
            for s in e.specs(layout):
                owners.setdefault(s.key, e)
    return owners


def truth_from_dict(raw: dict, layout: Layout, path: str = "<truth>") -> Truth:
    params_raw = raw.get("params", {})
    options = raw.get("options", {})
    owners = key_owner(layout, options)
    # temperature drift of order N: (n, N) arrays (CONTRACT.md section 7); one
    # order per sensor, the lower-order key padded with zero columns
    orders = {}
    for key, value in params_raw.items():
        base = split_suffix(key)[0]
        for sensor in ("accel", "gyro"):
            if base in (f"{sensor}_temp_bias", f"{sensor}_temp_scale"):
                try:
                    a = np.asarray(value, dtype=float)
                except (TypeError, ValueError):
                    raise InputError(f"{key}: not numeric", path) from None
                orders[sensor] = max(orders.get(sensor, 1), a.shape[1] if a.ndim == 2 else 1)
    temp_ref = float(options.get("temp_ref_degC", 25.0))
    for sensor, order in orders.items():
        eff = make_effect("temperature_drift", sensor, order=order, temp_ref=temp_ref)
        for sp in eff.specs(layout):
            owners[sp.key] = eff
    params, effects = {}, []
    for key, value in params_raw.items():
        base, factor = split_suffix(key)
        if base not in owners:
            raise InputError(f"unknown truth parameter {key!r}", path)
        eff = owners[base]
        spec = next(s for s in eff.specs(layout) if s.key == base)
        try:
            arr = np.asarray(value, dtype=float) * factor
            arr = np.broadcast_to(arr, spec.shape).copy() if arr.ndim == 0 else arr
            if len(spec.shape) == 2 and arr.ndim == 1 and arr.shape[0] == spec.shape[0]:
                arr = np.column_stack([arr, np.zeros((arr.shape[0], spec.shape[1] - 1))])
            elif len(spec.shape) == 2 and arr.ndim == 2 and arr.shape[1] < spec.shape[1]:
                arr = np.column_stack([arr, np.zeros((arr.shape[0],
                                                      spec.shape[1] - arr.shape[1]))])
        except (TypeError, ValueError):
            raise InputError(f"{key}: not numeric", path) from None
        if arr.shape != spec.shape:
            raise InputError(f"{key}: shape {arr.shape}, expected {spec.shape}", path)
        params[base] = arr
        if eff not in effects:
            effects.append(eff)
    noise = dict(DEFAULT_NOISE)
    for key, value in raw.get("noise", {}).items():
        base, factor = split_suffix(key)
        noise[base] = np.asarray(value, dtype=float) * factor
    out = raw.get("output", {})
    counts = out.get("units", "si") == "count"
    return Truth(ImuModel(tuple(effects), layout), params, noise, counts,
                 bool(out.get("quantize", counts)))


def default_truth(layout: Layout, rng: np.random.Generator) -> Truth:
    """A random MEMS-grade unit: bias and K (or RIMU installation errors) for
    both sensors, each entry drawn N(0, typical) from the catalogue's typical sizes."""
    effects = []
    for s in ("accel", "gyro"):
        effects.append(make_effect("bias", s))
        effects.append(make_effect("installation" if layout.redundant else "scale_misalignment", s))
    model = ImuModel(tuple(effects), layout)
    return Truth(model, model.random_params(rng), dict(DEFAULT_NOISE))
