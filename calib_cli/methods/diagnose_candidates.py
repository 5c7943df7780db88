"""Which effects a model lacks, whether the experiment can excite them, and
how a calibration engineer names them.

``candidates`` returns the effects to try next (each a catalogue effect on one
sensor) and, for the rest of the catalogue, why this experiment cannot test
them. ``describe`` turns a fitted effect into words.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib_cli.methods.diagnose_problem import Problem
from calib_cli.model.effects import Effect, Excitation, make_effect

G0 = 9.80665
LEVEL_G = 0.05  # input levels closer than this (in g) count as one


@dataclass(frozen=True)
class Candidate:
    name: str  # the contract's effect name
    sensor: str  # "accel", "gyro" or "" (time offset: both)
    effect: Effect

    @property
    def key(self) -> str:
        return effect_key(self.name, self.sensor)


def effect_key(name: str, sensor: str) -> str:
    """How a report names an effect on one sensor: "gyro temperature_drift",
    "lever_arm", "accel_nonlinearity"."""
    if not sensor or name.startswith(sensor + "_"):
        return name
    return f"{sensor} {name}"


def _levels(u: np.ndarray, g: float) -> int:
    """Number of distinct input levels (LEVEL_G apart) along one axis."""
    q = np.unique(np.round(u / (LEVEL_G * g)))
    return len(q)


def excitation(pb: Problem, base_structure: str = "full") -> Excitation:
    """What the problem's record excites (the effects' ``not_excited`` rules read it)."""
    axes = pb.layout.axes()
    fb = pb.bin_mean(pb.kin.f) @ axes.T  # input along each channel
    levels = max(_levels(fb[:, i], pb.g) for i in range(fb.shape[1]))
    both = False
    if "gyro" in pb.sensors:
        wb = pb.bin_mean(pb.kin.w) @ axes.T
        both = any(np.any(wb[:, i] > 0.05) and np.any(wb[:, i] < -0.05)
                   for i in range(wb.shape[1]))
    span = None
    if pb.kin.temp is not None and np.all(np.isfinite(pb.kin.temp)):
        span = float(np.ptp(pb.kin.temp))
    return Excitation(pb.method, tuple(pb.sensors), base_structure, int(levels), bool(both),
                      span, pb.n_bins, pb.layout.n_cycles > 0, pb.layout.redundant,
                      fixed_scale=pb.how.fixed_scale)


def catalogue_order(pb: Problem, base_structure: str = "full") -> list[Candidate]:
    """Every optional catalogue effect the method could take, in the order the rounds
    try them (whether this record excites it or not)."""
    out = []
    has_gyro = "gyro" in pb.sensors

    def add(name, sensor, **opts):
        out.append(Candidate(name, sensor, make_effect(name, sensor or "accel", **opts)))

    # "lower" where the accelerometers fix the instrument frame (the method's description
    # says so, or the positions' attitudes are unknown)
    add("misalignment", "accel",
        structure="lower" if (pb.how.misalignment == "lower" or pb.scalar) else "full")
    if has_gyro:
        add("misalignment", "gyro", structure="full")
    add("accel_nonlinearity", "accel")
    add("scale_asymmetry", "accel")
    if has_gyro:
        add("scale_asymmetry", "gyro")
        add("g_sensitivity", "gyro")
    for s in pb.sensors:
        add("temperature_drift", s)
    for s in pb.sensors:
        add("bias_random_walk", s)
        add("bias_instability", s)
    add("lever_arm", "")
    add("proof_mass_offsets", "")
    add("time_offset", "")
    # any other catalogue effect (a new class in model/effects.py): on every sensor, where
    # it is diagnosable and defined for this layout (Effect attributes); its own
    # excitation rule decides in candidates()
    for name, cls, defined in _extra_effects(pb):
        if defined:
            for s in ([""] if cls.sensorless else pb.sensors):
                add(name, s)
    return out


def _extra_effects(pb: Problem) -> list:
    """(name, class, defined for this record's layout) of the diagnosable catalogue
    effects beyond the ones catalogue_order lists by name."""
    from calib_cli.model.effects import CATALOGUE

    kind = "redundant" if pb.layout.redundant else "triad"
    return [(n, c, kind in c.layouts) for n, c in CATALOGUE.items()
            if n not in RULED and c.diagnosable]


def why_key(c: Candidate) -> str:
    """The key of the "untested" entry of a candidate (misalignment: one for both)."""
    return "misalignment" if c.name == "misalignment" else c.key


def candidates(pb: Problem, model, base_structure: str, tried_names: set
               ) -> tuple[list[Candidate], dict]:
    """(candidates to try, {effect key: why it cannot be tested}): each catalogue
    effect's own excitation rule (``Effect.not_excited``) on this record."""
    ex = excitation(pb, base_structure)
    out: list[Candidate] = []
    why: dict[str, str] = {}
    for c in catalogue_order(pb, base_structure):
        if c.key in tried_names:
            continue
        reason = c.effect.not_excited(ex)
        if reason:
            why.setdefault(why_key(c), reason)
        else:
            out.append(c)
    for name, _cls, defined in _extra_effects(pb):
        if not defined:
            why[name] = (f"not defined for a {'redundant' if pb.layout.redundant else 'triad'} "
                         "unit")
    return out, why


# effects in catalogue_order's list (the others: their class attributes)
RULED = {"bias", "scale_misalignment", "installation", "misalignment", "accel_nonlinearity",
         "scale_asymmetry", "g_sensitivity", "temperature_drift", "thermal_lag",
         "bias_random_walk", "bias_instability", "lever_arm", "proof_mass_offsets",
         "time_offset", "white_noise"}


def temperature_note(pb: Problem) -> str | None:
    """Whether a thermal drift can be told from a bias random walk."""
    if pb.kin.temp is None:
        return None
    T = pb.temp()
    dT = np.diff(T)
    if np.all(dT >= -1e-3) or np.all(dT <= 1e-3):
        return ("the temperature is monotonic in time, so a thermal drift and a slow bias "
                "drift (random walk) look alike here")
    return None


# -- words ---------------------------------------------------------------


def _fmt(v, s, factor, unit):
    if s is None or not np.isfinite(s):
        return f"{v * factor:.3g} (unobservable) {unit}"
    return f"{v * factor:.3g} +- {s * factor:.2g} {unit}"


def _largest(params, sigma, key):
    """(flat index, value, sigma) of the entry with the largest |value|/sigma."""
    v = np.asarray(params[key], float).ravel()
    s = np.asarray(sigma[key], float).ravel()
    z = np.where(s > 0, np.abs(v) / np.where(s > 0, s, 1), 0)
    z = np.where(np.isfinite(z), z, 0)
    i = int(np.argmax(z))
    return i, v[i], s[i]


AX = "xyz"


class _Channels:
    """Channel names: x, y, z of a triad; sensor numbers of a redundant unit."""

    redundant = False

    def __getitem__(self, i):
        return f"#{i}" if self.redundant else AX[i]


CH = _Channels()


def describe(c: Candidate, params: dict, sigma: dict, pb: Problem | None = None) -> str:
    """The effect in a calibration engineer's words, with its largest term (data in
    counts: output-side values divided by the counts per SI unit, approximately SI)."""
    if pb is not None:
        params = {k: np.asarray(v, float) / pb.scale_of(k) for k, v in params.items()}
        sigma = {k: np.asarray(v, float) / pb.scale_of(k) for k, v in sigma.items()}
    CH.redundant = bool(pb is not None and pb.layout.redundant)
    n, s = c.name, c.sensor
    if n == "lever_arm":
        L = np.asarray(params["lever_arm"])
        i, v, sg = _largest(params, sigma, "lever_arm")
        mm = np.linalg.norm(L, axis=1) * 1e3
        return ("lever arm: the accelerometers sit off the table axis, so the centripetal "
                "acceleration grows with rate^2; distance from the axis "
                + ", ".join(f"{x:.1f} mm" for x in mm) + " per cycle (largest term "
                f"{_fmt(v, sg, 1e3, 'mm')})")
    if n == "proof_mass_offsets":
        i, v, sg = _largest(params, sigma, "proof_mass_offsets")
        return (f"size effect: the three proof masses sit apart (accelerometer {CH[i // 3]} "
                f"offset along {AX[i % 3]} {_fmt(v, sg, 1e3, 'mm')})")
    if n == "time_offset":
        lag = _fmt(float(params["time_offset"]), float(sigma["time_offset"]), 1e3, "ms")
        return ("time offset between the IMU and the table: the residual follows the rate "
                f"change; the IMU lags by {lag}")
    if n == "g_sensitivity":
        i, v, sg = _largest(params, sigma, "gyro_D")
        return (f"gyro g-sensitivity: the gyro bias moves with the specific force (gyro "
                f"{CH[i // 3]} per g along {AX[i % 3]}: "
                f"{_fmt(v, sg, 180 / np.pi * 3600 * G0, 'deg/h/g')})")
    if n == "accel_nonlinearity":
        i, v, sg = _largest(params, sigma, "accel_nonlinearity")
        return (f"accelerometer nonlinearity: the scale factor changes with the input, a "
                f"term in f^2 (axis {CH[i]}: {_fmt(v, sg, G0 * 1e6, 'ug/g^2')})")
    if n == "scale_asymmetry":
        key = f"{s}_scale_asymmetry"
        i, v, sg = _largest(params, sigma, key)
        return (f"{s} scale-factor asymmetry: different scale for positive and negative "
                f"inputs (axis {CH[i]}: {_fmt(v, sg, 1e6, 'ppm')})")
    if n == "temperature_drift":
        i, v, sg = _largest(params, sigma, f"{s}_temp_bias")
        j, w, sw = _largest(params, sigma, f"{s}_temp_scale")
        f, u = ((1e3 / G0, "mg/degC") if s == "accel" else (180 / np.pi * 3600, "deg/h/degC"))
        return (f"{s} thermal drift: bias and scale follow the temperature (bias {CH[i]} "
                f"{_fmt(v, sg, f, u)}; scale {CH[j]} {_fmt(w, sw, 1e6, 'ppm/degC')})")
    if n == "misalignment":
        i, v, sg = _largest(params, sigma, f"{s}_misalignment")
        return (f"{s} axis misalignment / cross-coupling: axis {AX[i // 3]} senses input "
                f"along {AX[i % 3]} ({_fmt(v, sg, 1e3, 'mrad')})")
    if n in ("bias_instability", "bias_random_walk"):  # one figure per channel
        flicker = n == "bias_instability"
        v = np.asarray(params[f"{s}_{'bias_instability' if flicker else 'bias_rw'}"])
        f, u = ((1e6 / G0, "ug") if s == "accel" else (180 / np.pi * 3600, "deg/h"))
        figures = ", ".join(f"{x * f:.3g}" for x in v)
        if flicker:
            return (f"{s} bias instability (flicker): the bias wanders with a 1/f spectrum, "
                    f"correlated over seconds to hours; Allan bias-instability figure B "
                    f"{figures} {u}")
        return (f"{s} bias random walk: the bias wanders slowly over the record (density "
                f"{figures} {u}/sqrt(s))")
    return c.effect.describe(params, sigma)  # any other effect: its own words
