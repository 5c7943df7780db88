"""The effect catalogue: every physical error term, written once.

Each effect is one small class: its catalogue name (CONTRACT.md section 5),
the sensor it acts on, its parameters (keys, shapes, units, typical sizes)
and a forward step that adds its contribution to the sensor outputs. The
simulator runs a model forward, the estimators fit its parameters through
the same forward function, and ``diagnose`` tries the effects a model lacks.

The forward pipeline of one sensor (see ``ImuModel.predict``) runs the
effects by stage:

    SHIFT      the inputs in time (time offset)
    INPUT      the input vector each channel sees (lever arm, proof masses)
    TRANSFER   input -> output (scale/misalignment K, or RIMU installation)
    CORRECTION terms on the channel's own input u (nonlinearity, asymmetry,
               temperature, misalignment from a diagonal base)
    ADDITIVE   terms independent of the channel's input (bias, g-sensitivity)
    STOCHASTIC noise processes (bias random walk, flicker); zero in the
               deterministic prediction, realised only by the simulator
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from calib_cli.geometry import Layout  # noqa: F401  (defined in the base layer; re-exported)
from calib_cli.model.frames import skew
from calib_cli.model.kinematics import Kinematics, rigid_accel

SHIFT, INPUT, TRANSFER, CORRECTION, ADDITIVE, STOCHASTIC = range(6)

TEMP_REF_C = 25.0  # degC: reference temperature of the temperature-drift terms


@dataclass(frozen=True)
class Excitation:
    """What a record excites, as the effects' ``not_excited`` rules read it
    (computed from a recording by ``methods.diagnose_candidates.excitation``).

    accel_levels: the most distinct specific-force levels (0.05 g apart) on one
    accelerometer axis; gyro_both_signs: some gyro axis turned both ways;
    temp_span: degC spanned by the recorded temperature (None: none recorded);
    n_bins: 0.5 s bins; base: "full" or "diagonal" (the base model's K); fixed_scale:
    why the method's base model has no scale factors ("" where it has: its ``Diagnose``
    description, methods/method.py)."""

    method: str = "accel"
    sensors: tuple = ("accel",)
    base: str = "full"
    accel_levels: int = 0
    gyro_both_signs: bool = False
    temp_span: float | None = None
    n_bins: int = 0
    rotating: bool = False
    redundant: bool = False
    gravity_3d: bool = True  # static positions with gravity directions spanning 3-D
    fixed_scale: str = ""  # why the method's base model has no scale factors (K = I)


_NEEDS_ROTATION = "needs rotation (a turntable): the experiment has only static positions"


@dataclass(frozen=True)
class ParamSpec:
    """One parameter array of an effect.

    key: name in ``params`` (the contract's keys). shape: array shape.
    unit: SI unit. typical: 1-sigma size on a typical MEMS unit, SI (prior
    for simulation defaults and scale for the optimiser). identity: the
    neutral value is the identity matrix (else zeros). fixed: entries fixed
    by convention (value 0 or 1, sigma 0), same shape, or None.
    display: (factor, unit) for the terminal.
    """

    key: str
    shape: tuple
    unit: str
    typical: float
    identity: bool = False
    fixed: np.ndarray | None = None
    display: tuple = (1.0, "")

    def neutral(self) -> np.ndarray:
        if self.identity:
            return np.eye(self.shape[0])
        return np.zeros(self.shape)

    def fixed_mask(self) -> np.ndarray:
        return np.zeros(self.shape, bool) if self.fixed is None else self.fixed


class ApplyContext:
    """Working state of one sensor's forward pass."""

    def __init__(self, kin: Kinematics, layout: Layout, sensor: str):
        self.kin = kin
        self.layout = layout
        self.sensor = sensor
        n = layout.n
        src = kin.f if sensor == "accel" else kin.w
        self.F = np.repeat(src[:, None, :], n, axis=1)  # (N, n, 3) input vector of each channel
        self.f_ref = kin.f  # specific force at the unit's reference point
        self.u = None  # (N, n) input along each channel's sensitive axis
        self.y_transfer = None  # (N, n) output of the transfer stage, (K f)_i
        self.y = None  # (N, n) output


@dataclass(frozen=True)
class Effect:
    """Base class. ``sensor`` is "accel" or "gyro".

    Everything about an effect lives on its class (docs/architecture.md, "A new
    effect"): the forward step (``apply``), the parameters (``specs``: keys, shapes,
    SI units, typical sizes, display units), the noise realisation of a stochastic
    effect (``realisation``), and these class attributes, read by the simulator, the
    emulator, diagnose, export and the displays:

    - ``description``: one line in a calibration engineer's words (diagnose, docs);
    - ``sensorless``: one instance for the unit, made without a sensor argument;
    - ``layouts``: the unit layouts it applies to ("triad", "redundant");
    - ``export``: how ``calib export`` writes it: "linear" (part of the affine
      correction), "thermal" (evaluated first), "input" (an input-side term, not part
      of the correction), "noise" (a noise term, never in a calibration), "none"
      (refused: the numerical inverse of ``calib apply`` only);
    - ``diagnosable``: ``calib diagnose`` may try it where the data excite it;
    - ``noise_table``: its parameters are a truth file's [noise] table, not [params].
    """

    sensor: str
    name: str = field(default="", init=False)
    stage: int = field(default=ADDITIVE, init=False)

    description = ""
    sensorless = False
    layouts = ("triad", "redundant")
    export = "none"
    diagnosable = True
    noise_table = False

    def describe(self, params: dict, sigma: dict) -> str:
        """The fitted effect in words with its largest term, in display units."""
        best = None
        for sp in self.specs(_describe_layout(params, self.specs)):
            if sp.key not in params:
                continue
            v = np.ravel(np.asarray(params[sp.key], dtype=float))
            sg = np.ravel(np.asarray(sigma.get(sp.key, np.full(v.shape, np.nan)), dtype=float))
            z = np.abs(v) / np.where(sg > 0, sg, np.inf)
            i = int(np.nanargmax(z)) if np.any(np.isfinite(z)) else int(np.argmax(np.abs(v)))
            if best is None or abs(v[i]) * sp.display[0] > best[0]:
                best = (abs(v[i]) * sp.display[0], sp, i, v[i], sg[i])
        text = self.description or self.label
        if best is None:
            return text
        _, sp, i, v, sg = best
        f, unit = sp.display if sp.display != (1.0, "") else (1.0, sp.unit)
        # a thermal polynomial's column k is the coefficient of dT^(k+1): its unit's power
        shape = np.shape(params[sp.key])
        power = int(np.unravel_index(i, shape)[-1]) + 1 if len(shape) == 2 and \
            "^k" in unit else 1
        unit = unit.replace("^k", "" if power == 1 else f"^{power}")
        return (f"{text} (largest term {sp.key}[{i}] = {v * f:.3g} +- {sg * f:.2g} "
                f"{unit})").replace(" +- nan", "")

    def specs(self, layout: Layout) -> list[ParamSpec]:
        return []

    def apply(self, p: dict, ctx: ApplyContext) -> None:
        """Add this effect's contribution to ctx (in place)."""

    # -- derivatives (model/jacobian.py). An effect that has them sets has_derivatives;
    # for one that has not (a time shift, a RIMU installation) the Jacobian takes central
    # differences of the forward model. ``linear_in_kinematics``: the effect's output is
    # linear in the kinematics (specific force, rates, the centripetal operator), so its
    # mean over an interval is its value at the interval's mean kinematics; False for
    # terms such as u^2 or |u|, which an interval's mean input does not give.
    has_derivatives = False
    linear_in_kinematics = True

    def d_param(self, p: dict, ctx: ApplyContext, key: str, flats) -> np.ndarray:
        """The derivative of this effect's stage output by the entries ``flats`` (flat
        indices) of its parameter ``key``: (N, n, len(flats)) of y (TRANSFER: of the
        transfer output); INPUT effects return (dF (N, n, 3, k), df_ref (N, 3, k) or None)."""
        raise NotImplementedError

    def gain(self, p: dict, ctx: ApplyContext) -> np.ndarray | None:
        """TRANSFER: d y_i / d F_i (N, n, 3) (or (n, 3)); CORRECTION: what the term adds to
        it; None: nothing."""
        return None

    def transfer_gain(self, p: dict, ctx: ApplyContext) -> np.ndarray | None:
        """CORRECTION: d(term) / d y_transfer (N, n), for a term on the transfer output."""
        return None

    def d_fref(self, p: dict, ctx: ApplyContext) -> np.ndarray | None:
        """ADDITIVE: d(term) / d f_ref (N, n, 3) (or (n, 3)), the specific force at the
        reference point (g-sensitivity)."""
        return None

    def d_kin(self, p: dict, ctx: ApplyContext, name: str):
        """INPUT: (dF, df_ref) by a kinematics input: "cen" (N, n, 3, 3, 3) and (N, 3, 3, 3),
        "dw" and "w" (N, n, 3, 3) and (N, 3, 3); df_ref None where f_ref does not move."""
        return None, None

    def realisation(self, p: dict, layout: Layout, fs: float, seed: int):
        """The stateful noise realisation of a stochastic effect: ``r.next(kin)`` gives
        the next len(kin) samples (N, n), drawn as a function of the sample index and
        ``seed`` alone, so the simulator (one call) and the emulator (chunks) get the
        same numbers. None for a deterministic effect."""
        return None

    def realise(self, p: dict, kin: Kinematics, layout: Layout, rng) -> np.ndarray:
        """A random realisation (N, n) over a whole record (seeded from ``rng``)."""
        dt = float(np.median(np.diff(kin.t))) if len(kin) > 1 else 1.0
        r = self.realisation(p, layout, 1.0 / dt, int(rng.integers(2**62)))
        return 0.0 if r is None else r.next(kin)

    # what experiment excites the effect, and what to record when a record does not
    # (``calib fit --with``, ``calib diagnose``; docs/diagnose.md)
    excites = ""
    record = ""
    noise_term = False  # a noise-model term: widens sigma, never applied or exported

    def not_excited(self, ex: "Excitation") -> str | None:
        """Why a record with this excitation cannot determine the effect (None: it can)."""
        return None

    @property
    def label(self) -> str:
        return f"{self.sensor} {self.name}" if self.sensor else self.name

    def _key(self, suffix: str) -> str:
        return f"{self.sensor}_{suffix}"


_ACC_DISPLAY = (1e3 / 9.80665, "mg")
_GYR_DISPLAY = (180 / np.pi * 3600, "deg/h")


# ---------------------------------------------------------------------------
# additive terms


@dataclass(frozen=True)
class Bias(Effect):
    """Constant output offset b (m/s^2 or rad/s per channel)."""

    description = "constant output offset"
    export = "linear"

    name: str = field(default="bias", init=False)
    stage: int = field(default=ADDITIVE, init=False)

    def specs(self, layout):
        acc = self.sensor == "accel"
        return [ParamSpec(self._key("bias"), (layout.n,), "m/s^2" if acc else "rad/s",
                          0.05 if acc else 5e-3,
                          display=_ACC_DISPLAY if acc else _GYR_DISPLAY)]

    has_derivatives = True

    def apply(self, p, ctx):
        ctx.y = ctx.y + p[self._key("bias")]

    def d_param(self, p, ctx, key, flats):
        out = np.zeros((len(ctx.kin), ctx.layout.n, len(flats)))
        for q, i in enumerate(flats):
            out[:, i, q] = 1.0
        return out


@dataclass(frozen=True)
class GSensitivity(Effect):
    """Gyro g-sensitivity: W += D f, f the specific force at the triad's reference point."""

    description = "gyro g-sensitivity: the gyro bias moves with the specific force"
    sensorless = True
    export = "linear"

    sensor: str = "gyro"
    name: str = field(default="g_sensitivity", init=False)
    stage: int = field(default=ADDITIVE, init=False)

    excites = "static positions with gravity along each body axis (both signs), gyros recorded"
    record = "static positions with each axis up and down, gyros recorded"

    def not_excited(self, ex):
        if "gyro" not in ex.sensors:
            return "no gyro data in this method's record"
        if not ex.gravity_3d:
            return "the static positions' gravity directions do not span all three axes"
        return None

    def specs(self, layout):
        return [ParamSpec("gyro_D", (layout.n, 3), "(rad/s)/(m/s^2)", 1e-4,
                          display=(180 / np.pi * 3600 * 9.80665, "deg/h/g"))]

    has_derivatives = True

    def apply(self, p, ctx):
        ctx.y = ctx.y + ctx.f_ref @ p["gyro_D"].T

    def d_param(self, p, ctx, key, flats):
        out = np.zeros((len(ctx.kin), ctx.layout.n, len(flats)))
        for q, flat in enumerate(flats):
            a, b = divmod(int(flat), 3)
            out[:, a, q] = ctx.f_ref[:, b]
        return out

    def d_fref(self, p, ctx):
        return np.asarray(p["gyro_D"], float)


# ---------------------------------------------------------------------------
# transfer: input -> output


def _k_mask(structure: str) -> np.ndarray | None:
    if structure == "full":
        return None
    if structure == "lower":
        return np.triu(np.ones((3, 3), bool), 1)
    if structure == "diagonal":
        return ~np.eye(3, dtype=bool)
    raise ValueError(f"unknown K structure {structure!r}")


@dataclass(frozen=True)
class ScaleMisalignment(Effect):
    """Triad transfer matrix K: y_i = sum_j K_ij F_ij (F_i the input vector at channel i).

    structure: "full" (9 free), "lower" (the instrument frame fixed by the
    sensor triad itself: upper triangle 0), "diagonal" (scale factors only).
    """

    description = "scale factor and misalignment (K)"
    layouts = ("triad",)
    export = "linear"

    structure: str = "full"
    name: str = field(default="scale_misalignment", init=False)
    stage: int = field(default=TRANSFER, init=False)

    def specs(self, layout):
        return [ParamSpec(self._key("K"), (3, 3), "-", 3e-3, identity=True,
                          fixed=_k_mask(self.structure), display=(1.0, ""))]

    has_derivatives = True

    def apply(self, p, ctx):
        K = p[self._key("K")]
        ctx.y = np.einsum("ij,nij->ni", K, ctx.F)

    def d_param(self, p, ctx, key, flats):
        return _matrix_columns(ctx, flats)

    def gain(self, p, ctx):
        return np.asarray(p[self._key("K")], float)


@dataclass(frozen=True)
class Installation(Effect):
    """RIMU channel i: y_i = (1 + ks_i) S_i . x, S_i from El0 + dEl, Az0 - dAz."""

    description = "scale error and installation angles of each single-axis sensor"
    layouts = ("redundant",)
    export = "none"

    name: str = field(default="installation", init=False)
    stage: int = field(default=TRANSFER, init=False)

    def specs(self, layout):
        return [ParamSpec(self._key("scale_error"), (layout.n,), "-", 5e-3, display=(1e6, "ppm")),
                ParamSpec(self._key("dEl"), (layout.n,), "rad", 0.01, display=(1e3, "mrad")),
                ParamSpec(self._key("dAz"), (layout.n,), "rad", 0.01, display=(1e3, "mrad"))]

    def apply(self, p, ctx):
        S = ctx.layout.axes(p[self._key("dEl")], p[self._key("dAz")])
        scale = 1.0 + p[self._key("scale_error")]
        ctx.y = np.einsum("ij,nij->ni", S, ctx.F) * scale


# ---------------------------------------------------------------------------
# corrections on the channel's own input u


@dataclass(frozen=True)
class Misalignment(Effect):
    """Off-diagonal part of K for a model that starts from diagonal scale factors.

    y_i += sum_{j != i} M_ij F_ij. structure "full" (6 terms) or "lower" (3).
    """

    description = "misalignment: the axes are not orthogonal (from a diagonal base)"
    export = "linear"

    structure: str = "full"
    name: str = field(default="misalignment", init=False)
    stage: int = field(default=CORRECTION, init=False)

    excites = ("a base model with diagonal scale factors (--base diagonal) and inputs along "
               "several axes")
    record = "inputs along every axis, and fit with --base diagonal"

    def not_excited(self, ex):
        if ex.fixed_scale:
            return ex.fixed_scale
        if ex.redundant:
            return ("a redundant unit's base model has each sensor's direction (dEl, dAz): "
                    "there is no triad misalignment")
        if ex.base != "diagonal":
            return ("the base model already has full scale/misalignment (use --base diagonal "
                    "to test it)")
        return None

    def specs(self, layout):
        fixed = np.eye(3, dtype=bool)
        if self.structure == "lower":
            fixed = fixed | np.triu(np.ones((3, 3), bool), 1)
        return [ParamSpec(self._key("misalignment"), (3, 3), "-", 2e-3, fixed=fixed)]

    has_derivatives = True

    def apply(self, p, ctx):
        ctx.y = ctx.y + np.einsum("ij,nij->ni", p[self._key("misalignment")], ctx.F)

    def d_param(self, p, ctx, key, flats):
        return _matrix_columns(ctx, flats)

    def gain(self, p, ctx):
        return np.asarray(p[self._key("misalignment")], float)


@dataclass(frozen=True)
class Nonlinearity(Effect):
    """Quadratic scale term per channel: y_i += k2_i u_i^2 (k2 in 1/(input unit))."""

    description = "accelerometer nonlinearity: the output grows with the square of the input"
    export = "none"

    name: str = field(default="accel_nonlinearity", init=False)
    stage: int = field(default=CORRECTION, init=False)

    excites = ("inputs of at least three sizes on an axis (0 g counts); told apart from scale "
               "asymmetry only with positions at 35-55 deg inclination")
    record = "positions with an axis at 0 g besides +-g, better tilted 35-55 deg"

    def not_excited(self, ex):
        if ex.accel_levels < 3:
            return ("every axis sees only +-g: the quadratic term needs inputs other than +-g "
                    "on the axis (0 g counts)")
        return None

    def specs(self, layout):
        acc = self.sensor == "accel"
        return [ParamSpec(self._key("nonlinearity"), (layout.n,),
                          "1/(m/s^2)" if acc else "1/(rad/s)", 5e-5 if acc else 1e-3,
                          display=(9.80665 * 1e6, "ug/g^2") if acc else (1.0, ""))]

    has_derivatives = True
    linear_in_kinematics = False

    def apply(self, p, ctx):
        ctx.y = ctx.y + p[self._key("nonlinearity")] * ctx.u**2

    def d_param(self, p, ctx, key, flats):
        return _channel_columns(ctx, flats, ctx.u**2)

    def gain(self, p, ctx):
        k2 = np.asarray(p[self._key("nonlinearity")], float)
        return (2.0 * k2 * ctx.u)[:, :, None] * ctx.layout.axes()[None]


@dataclass(frozen=True)
class ScaleAsymmetry(Effect):
    """Different scale for positive and negative input: y_i += a_i |u_i|."""

    description = "scale asymmetry: a different scale factor for positive and negative inputs"
    export = "none"

    name: str = field(default="scale_asymmetry", init=False)
    stage: int = field(default=CORRECTION, init=False)

    @property
    def excites(self):
        if self.sensor == "gyro":
            return "rotations both ways about an axis (faster than 3 deg/s)"
        return ("inputs of both signs at four or more sizes (tilts between 0 and +-g; at 0 "
                "and +-g only it looks like nonlinearity)")

    @property
    def record(self):
        if self.sensor == "gyro":
            return "rotations both ways about each axis"
        return "positions with the axes tilted 35-55 deg"

    def not_excited(self, ex):
        if self.sensor == "gyro":
            return None if ex.gyro_both_signs else ("no axis is turned both ways at more than "
                                                    "3 deg/s")
        if ex.accel_levels >= 4:
            return None
        if ex.accel_levels == 3:
            return ("the axes see only 0 and +-g, where a|u| and k2 u^2 are the same "
                    "signature: telling scale asymmetry from nonlinearity needs intermediate "
                    "tilts (add positions with the axis tilted 45 deg)")
        return "every axis sees only +-g: needs inputs of other sizes"

    def specs(self, layout):
        return [ParamSpec(self._key("scale_asymmetry"), (layout.n,), "-", 5e-4,
                          display=(1e6, "ppm"))]

    has_derivatives = True
    linear_in_kinematics = False

    def apply(self, p, ctx):
        ctx.y = ctx.y + p[self._key("scale_asymmetry")] * np.abs(ctx.u)

    def d_param(self, p, ctx, key, flats):
        return _channel_columns(ctx, flats, np.abs(ctx.u))

    def gain(self, p, ctx):
        a = np.asarray(p[self._key("scale_asymmetry")], float)
        return (a * np.sign(ctx.u))[:, :, None] * ctx.layout.axes()[None]


def temp_poly(coef: np.ndarray, dT: np.ndarray) -> np.ndarray:
    """sum_k c_ik dT^(k+1) for each sample and channel: (N, n).

    coef: (n,) (order 1) or (n, N) with column k the coefficient of
    dT^(k+1) (CONTRACT.md section 7); dT: (N,) temperature minus T_ref."""
    c = np.asarray(coef, dtype=float)
    if c.ndim == 1:
        c = c[:, None]
    powers = np.stack([dT ** (k + 1) for k in range(c.shape[1])], axis=1)  # (N, order)
    return powers @ c.T


@dataclass(frozen=True)
class TemperatureDrift(Effect):
    """Bias and scale polynomial in T - T_ref (CONTRACT.md section 7):

        y_i = b_i + sum_k bT_ik dT^(k+1) + (1 + sum_k sT_ik dT^(k+1)) (K f)_i

    ``order`` N: parameters of shape (n,) for N = 1, (n, N) otherwise,
    column k the coefficient of dT^(k+1). ``temp_ref``: T_ref, degC.
    The scale term multiplies the transfer stage's output (K f)_i. Files
    written before this form (their model description has no ``order``)
    held a scale term on the nominal input u_i; ``scale_on = "input"``
    keeps reading them as they were fitted (docs/thermal.md).
    """

    description = "temperature drift of bias and scale factor"
    export = "thermal"

    order: int = 1
    temp_ref: float = TEMP_REF_C
    scale_on: str = "transfer"
    name: str = field(default="temperature_drift", init=False)
    stage: int = field(default=CORRECTION, init=False)

    excites = ("a recorded temperature spanning >= 1 degC, best going up and down (monotonic, "
               "it looks like a bias random walk)")
    record = "the temperature column, spanning several degC up and down (a chamber or warm-up)"

    def not_excited(self, ex):
        if ex.temp_span is None:
            return "no temperature recorded"
        if ex.temp_span < 1.0:
            return f"the temperature spans only {ex.temp_span:.2f} degC (needs >= 1 degC)"
        return None

    def specs(self, layout):
        acc = self.sensor == "accel"
        shape = (layout.n,) if self.order == 1 else (layout.n, self.order)
        return [ParamSpec(self._key("temp_bias"), shape,
                          "m/s^2/degC^k" if acc else "rad/s/degC^k", 1e-3 if acc else 1e-4,
                          display=(1e3 / 9.80665, "mg/degC^k") if acc else (180 / np.pi * 3600,
                                                                            "deg/h/degC^k")),
                ParamSpec(self._key("temp_scale"), shape, "1/degC^k", 1e-4,
                          display=(1e6, "ppm/degC^k"))]

    has_derivatives = True

    def apply(self, p, ctx):
        if ctx.kin.temp is None:
            return
        dT = np.asarray(ctx.kin.temp, dtype=float) - self.temp_ref
        base = ctx.u if self.scale_on == "input" else ctx.y_transfer
        ctx.y = ctx.y + temp_poly(p[self._key("temp_bias")], dT) + \
            temp_poly(p[self._key("temp_scale")], dT) * base

    def d_param(self, p, ctx, key, flats):
        out = np.zeros((len(ctx.kin), ctx.layout.n, len(flats)))
        if ctx.kin.temp is None:
            return out
        dT = np.asarray(ctx.kin.temp, dtype=float) - self.temp_ref
        base = ctx.u if self.scale_on == "input" else ctx.y_transfer
        for q, flat in enumerate(flats):
            i, k = divmod(int(flat), self.order)
            out[:, i, q] = dT ** (k + 1) * (base[:, i] if key == self._key("temp_scale") else 1.0)
        return out

    def _scale(self, p, ctx):
        dT = np.asarray(ctx.kin.temp, dtype=float) - self.temp_ref
        return temp_poly(p[self._key("temp_scale")], dT)

    def gain(self, p, ctx):
        if ctx.kin.temp is None or self.scale_on != "input":
            return None
        return self._scale(p, ctx)[:, :, None] * ctx.layout.axes()[None]

    def transfer_gain(self, p, ctx):
        if ctx.kin.temp is None or self.scale_on == "input":
            return None
        return self._scale(p, ctx)


def lag_temperature(t: np.ndarray, temp: np.ndarray, tau: float) -> np.ndarray:
    """The temperature of the sensing elements when they follow the unit's
    temperature sensor with a first-order lag of time constant tau (s):
    tau dTm/dt = T - Tm, Tm = T at the first sample; exact for T linear
    between samples (first-order hold)."""
    temp = np.asarray(temp, dtype=float)
    tau = abs(float(tau))
    if tau == 0.0 or len(temp) < 2:
        return temp.copy()
    dt = float(np.median(np.diff(t)))
    if not dt > 0:
        return temp.copy()
    a = np.exp(-dt / tau)
    c = 1.0 - tau * (1.0 - a) / dt
    from scipy.signal import lfilter

    # Tm_k = a Tm_{k-1} + (1 - a) T_{k-1} + c (T_k - T_{k-1}) = a Tm_{k-1} + c T_k + (1 - a - c) T_{k-1}
    x = temp - temp[0]
    y = lfilter([c, 1.0 - a - c], [1.0, -a], x)
    return y + temp[0]


@dataclass(frozen=True)
class ThermalLag(Effect):
    """The sensing elements follow the unit's temperature sensor with a
    first-order lag, time constant ``thermal_lag_tau`` (s): every
    temperature-dependent effect sees lag_temperature(t, temp, tau)."""

    description = "thermal lag: the sensor follows the measured temperature with a delay"
    sensorless = True
    export = "thermal"

    sensor: str = ""
    name: str = field(default="thermal_lag", init=False)
    stage: int = field(default=SHIFT, init=False)

    def specs(self, layout):
        return [ParamSpec("thermal_lag_tau", (), "s", 100.0, display=(1.0, "s"))]


# ---------------------------------------------------------------------------
# inputs: where the proof masses sit, and when


def lever_arm_per_sample(p: dict, kin: Kinematics) -> np.ndarray:
    """(N, 3) lever arm s in force at each sample (zero outside rotating cycles)."""
    s = np.asarray(p["lever_arm"], dtype=float)
    out = np.zeros((len(kin), 3))
    if kin.cycle is not None and len(s):
        on = kin.cycle >= 0
        out[on] = s[kin.cycle[on]]
    return out


def rigid_operator(kin: Kinematics, tangential: bool = True) -> np.ndarray:
    """d(rigid-body acceleration at r)/dr (N, 3, 3): the centripetal operator (``kin.cen``,
    else [w x]^2) plus [dw x] (tangential)."""
    if kin.cen is not None:
        C = np.array(kin.cen, dtype=float)
    else:
        w = np.asarray(kin.w, float)
        C = w[:, :, None] * w[:, None, :] - np.einsum("ni,ni->n", w, w)[:, None, None] * np.eye(3)
    if tangential:
        C = C + skew(kin.dw)
    return C


def rigid_input_derivative(kin: Kinematics, r: np.ndarray, name: str,
                           tangential: bool = True) -> np.ndarray | None:
    """d(rigid-body acceleration at r (N, 3))/d(kinematics input ``name``): "cen" (N, 3, 3, 3)
    [component, a, b] (the operator's entry (a, b)), "dw" (N, 3, 3), "w" (N, 3, 3) (where
    the rows carry no ``cen``), None for an input it does not depend on."""
    n = len(kin)
    if name == "cen" and kin.cen is not None:
        out = np.zeros((n, 3, 3, 3))
        for a in range(3):
            out[:, a, a, :] = r
        return out
    if name == "dw":
        return -skew(r) if tangential else np.zeros((n, 3, 3))
    if name == "w" and kin.cen is None:
        w = np.asarray(kin.w, float)
        wr = np.einsum("ni,ni->n", w, r)
        return (wr[:, None, None] * np.eye(3) + w[:, :, None] * r[:, None, :]
                - 2.0 * r[:, :, None] * w[:, None, :])
    return None


def _matrix_columns(ctx: ApplyContext, flats) -> np.ndarray:
    """d(sum_j M_ij F_ij)/d M_ab = F_ab in channel a: (N, n, len(flats))."""
    out = np.zeros((len(ctx.kin), ctx.layout.n, len(flats)))
    for q, flat in enumerate(flats):
        a, b = divmod(int(flat), 3)
        out[:, a, q] = ctx.F[:, a, b]
    return out


def _channel_columns(ctx: ApplyContext, flats, values: np.ndarray) -> np.ndarray:
    """d(c_i v_i)/d c_i = v_i in channel i: (N, n, len(flats))."""
    out = np.zeros((len(ctx.kin), ctx.layout.n, len(flats)))
    for q, i in enumerate(flats):
        out[:, int(i), q] = values[:, int(i)]
    return out


@dataclass(frozen=True)
class LeverArm(Effect):
    """Offset s of the unit's reference point from the table axis, one row per
    rotating cycle (body axes, m): f(r) = f + w x (w x r) + dw x r.

    tangential: include the dw x r term (needs angular acceleration).
    """

    description = "lever arm: the accelerometers sit off the table axis"
    sensorless = True
    export = "input"

    sensor: str = "accel"
    tangential: bool = True
    name: str = field(default="lever_arm", init=False)
    stage: int = field(default=INPUT, init=False)

    excites = "rotating segments (a turntable) at several rates"
    record = "rotating cycles on a turntable at two or more rates"

    def not_excited(self, ex):
        return None if ex.rotating else _NEEDS_ROTATION

    def specs(self, layout):
        return [ParamSpec("lever_arm", (layout.n_cycles, 3), "m", 0.1,
                          display=(1e3, "mm"))]

    has_derivatives = True

    def apply(self, p, ctx):
        s = lever_arm_per_sample(p, ctx.kin)
        df = rigid_accel(ctx.kin, s, self.tangential)
        ctx.F = ctx.F + df[:, None, :]
        ctx.f_ref = ctx.f_ref + df

    def d_param(self, p, ctx, key, flats):
        n = ctx.layout.n
        C = rigid_operator(ctx.kin, self.tangential)  # d(rigid accel)/d(position), (N, 3, 3)
        cyc = ctx.kin.cycle if ctx.kin.cycle is not None else np.full(len(ctx.kin), -1)
        dref = np.zeros((len(ctx.kin), 3, len(flats)))
        for q, flat in enumerate(flats):
            c, k = divmod(int(flat), 3)
            on = cyc == c
            dref[on, :, q] = C[on, :, k]
        return np.repeat(dref[:, None], n, axis=1), dref

    def d_kin(self, p, ctx, name):
        s = lever_arm_per_sample(p, ctx.kin)
        d = rigid_input_derivative(ctx.kin, s, name, self.tangential)
        if d is None:
            return None, None
        return np.repeat(d[:, None], ctx.layout.n, axis=1), d


@dataclass(frozen=True)
class ProofMassOffsets(Effect):
    """Position p_i of accelerometer i's proof mass relative to the triad's
    reference point (row i, m; p_ii = 0 by convention: the size effect)."""

    description = "size effect: the three proof masses sit apart"
    sensorless = True
    export = "input"

    sensor: str = "accel"
    tangential: bool = True
    name: str = field(default="proof_mass_offsets", init=False)
    stage: int = field(default=INPUT + 0, init=False)

    excites = "rotating segments with the table axis along different body axes"
    record = "rotating cycles on a turntable with each body axis along the table axis"

    def not_excited(self, ex):
        if not ex.rotating:
            return _NEEDS_ROTATION
        if ex.redundant:
            return "the redundant-unit model puts all sensors at one point (CONTRACT section 2)"
        return None

    def specs(self, layout):
        return [ParamSpec("proof_mass_offsets", (3, 3), "m", 5e-3,
                          fixed=np.eye(3, dtype=bool), display=(1e3, "mm"))]

    has_derivatives = True

    def apply(self, p, ctx):
        P = p["proof_mass_offsets"]
        for i in range(3):
            ctx.F[:, i, :] += rigid_accel(ctx.kin, P[i], self.tangential)

    def d_param(self, p, ctx, key, flats):
        C = rigid_operator(ctx.kin, self.tangential)
        out = np.zeros((len(ctx.kin), ctx.layout.n, 3, len(flats)))
        for q, flat in enumerate(flats):
            a, b = divmod(int(flat), 3)
            out[:, a, :, q] = C[:, :, b]
        return out, None

    def d_kin(self, p, ctx, name):
        P = np.asarray(p["proof_mass_offsets"], float)
        parts = [rigid_input_derivative(ctx.kin, np.broadcast_to(P[i], (len(ctx.kin), 3)), name,
                                        self.tangential) for i in range(3)]
        if parts[0] is None:
            return None, None
        return np.stack(parts, axis=1), None


def shift_kinematics(kin: Kinematics, tau: float) -> Kinematics:
    """The kinematics as seen by an IMU whose timestamps lag the truth by tau (s):
    the sample stamped t holds the state at t - tau (linear interpolation)."""
    if tau == 0.0:
        return kin
    tq = kin.t - tau

    def interp(a):
        return np.stack([np.interp(tq, kin.t, a[:, k]) for k in range(a.shape[1])], axis=1)

    return kin.with_(f=interp(kin.f), w=interp(kin.w), dw=interp(kin.dw))


@dataclass(frozen=True)
class TimeOffset(Effect):
    """IMU timestamps lag the table (the truth) by ``time_offset`` seconds."""

    description = "time offset between the IMU and the table"
    sensorless = True
    export = "none"

    sensor: str = ""
    name: str = field(default="time_offset", init=False)
    stage: int = field(default=SHIFT, init=False)

    excites = "rotating segments with rate changes"
    record = "rotating cycles with rate steps or ramps"

    def not_excited(self, ex):
        return None if ex.rotating else _NEEDS_ROTATION

    def specs(self, layout):
        return [ParamSpec("time_offset", (), "s", 2e-3, display=(1e3, "ms"))]


# ---------------------------------------------------------------------------
# stochastic bias processes (simulated, not in the deterministic prediction)


@dataclass(frozen=True)
class BiasRandomWalk(Effect):
    """The bias integrates white noise of density q (unit/sqrt(s)); for gyros
    this is rate random walk K."""

    description = "bias random walk: the bias wanders without bound"
    export = "noise"

    name: str = field(default="bias_random_walk", init=False)
    stage: int = field(default=STOCHASTIC, init=False)

    excites = "at least 20 bins (10 s), with static stretches long enough to show the wander"
    record = "longer static positions (minutes), or a static record for calib allan"
    noise_term = True

    def not_excited(self, ex):
        if ex.n_bins < 20:
            return "fewer than 20 bins (10 s): too short to see a wander"
        return None

    def specs(self, layout):
        acc = self.sensor == "accel"
        return [ParamSpec(self._key("bias_rw"), (layout.n,),
                          "m/s^2/sqrt(s)" if acc else "rad/s/sqrt(s)", 1e-4 if acc else 1e-5)]

    def realisation(self, p, layout, fs, seed):
        return _RandomWalk(np.asarray(p[self._key("bias_rw")], dtype=float),
                           NoiseStream(seed, _stream_id(self.label), layout.n))


# Flicker (1/f) bias noise as a sum of first-order Gauss-Markov processes with
# time constants two per decade from 0.1 s to 1e4 s and equal variance each.
# From the closed-form Allan variance of a Gauss-Markov process,
#   sigma^2(tau) = q^2 T^2/tau^2 (2 tau/T - 3 + 4 exp(-tau/T) - exp(-2 tau/T)),
# the sum's Allan deviation is flat within +-2 % from 1 s to 3000 s with a
# minimum of 1.0565 sigma_k; sigma_k = FLICKER_SCALE * B puts that minimum at
# 0.664 B, the IEEE 952 flicker floor (tests/test_model.py checks it).
FLICKER_TAUS = np.logspace(-1, 4, 11)
FLICKER_SCALE = 0.664 / 1.0565


@dataclass(frozen=True)
class BiasInstability(Effect):
    """Flicker bias noise of Allan bias-instability figure B (unit of the
    sensor), modelled as a sum of first-order Gauss-Markov processes whose
    time constants span FLICKER_TAUS."""

    description = "bias instability (flicker): the bias wanders within a floor"
    export = "noise"

    name: str = field(default="bias_instability", init=False)
    stage: int = field(default=STOCHASTIC, init=False)

    excites = "at least 20 bins (10 s), with static stretches long enough to show the wander"
    record = "longer static positions (minutes), or a static record for calib allan"
    noise_term = True

    def not_excited(self, ex):
        if ex.n_bins < 20:
            return "fewer than 20 bins (10 s): too short to see a wander"
        return None

    def specs(self, layout):
        acc = self.sensor == "accel"
        return [ParamSpec(self._key("bias_instability"), (layout.n,),
                          "m/s^2" if acc else "rad/s", 5e-4 if acc else 1e-4)]

    def realisation(self, p, layout, fs, seed):
        B = np.asarray(p[self._key("bias_instability")], dtype=float)
        return _Flicker(B, 1.0 / fs, seed, _stream_id(self.label), layout.n)


@dataclass(frozen=True)
class WhiteNoise(Effect):
    """White output noise: ``{sensor}_white`` per sample (1-sigma), or
    ``{sensor}_white_density`` per sqrt(Hz) (times sqrt(fs) per sample; used where
    given). A noise term: simulated and emulated, never a calibration parameter."""

    description = "white output noise"
    export = "noise"
    diagnosable = False
    noise_table = True

    name: str = field(default="white_noise", init=False)
    stage: int = field(default=STOCHASTIC, init=False)

    def specs(self, layout):
        acc = self.sensor == "accel"
        u = "m/s^2" if acc else "rad/s"
        return [ParamSpec(self._key("white"), (layout.n,), u, 3e-3 if acc else 1e-3),
                ParamSpec(self._key("white_density"), (layout.n,), u + "/sqrt(Hz)",
                          3e-4 if acc else 1e-4)]

    def realisation(self, p, layout, fs, seed):
        dens = np.asarray(p.get(self._key("white_density"), 0.0), dtype=float)
        sigma = (dens * np.sqrt(fs) if np.any(dens != 0)
                 else np.asarray(p.get(self._key("white"), 0.0), dtype=float))
        return _White(np.broadcast_to(sigma, (layout.n,)).astype(float),
                      NoiseStream(seed, _stream_id(self.label), layout.n))


class NoiseStream:
    """Standard normal numbers per sample index: blocks of BLOCK samples, each from
    its own generator seeded by (seed, stream key, block), so any chunking of the
    same index range gives the same numbers."""

    BLOCK = 4096

    def __init__(self, seed: int, key, dim: int):
        self.seed = int(seed)
        self.key = tuple(int(k) for k in np.atleast_1d(key))
        self.dim = dim
        self._block, self._data = None, None

    def normal(self, k0: int, n: int) -> np.ndarray:
        B, out, k = self.BLOCK, np.empty((n, self.dim)), k0
        while k < k0 + n:
            b = k // B
            if self._block != b:
                rng = np.random.default_rng([self.seed, *self.key, b])
                self._block, self._data = b, rng.standard_normal((B, self.dim))
            a = k - b * B
            m = min(B - a, k0 + n - k)
            out[k - k0:k - k0 + m] = self._data[a:a + m]
            k += m
        return out


def _stream_id(label: str) -> int:
    """A stable integer per effect (the random streams of different effects differ)."""
    import zlib

    return zlib.crc32(label.encode())


class _White:
    def __init__(self, sigma, stream):
        self.sigma, self.stream, self.k = sigma, stream, 0

    def next(self, kin):
        n = len(kin)
        out = self.stream.normal(self.k, n) * self.sigma
        self.k += n
        return out


class _RandomWalk:
    """b_k = b_{k-1} + q sqrt(t_k - t_{k-1}) w_k, starting at 0 (first step dt = 0)."""

    def __init__(self, q, stream):
        self.q, self.stream, self.k = q, stream, 0
        self.t_last, self.b_last = None, np.zeros(stream.dim)

    def next(self, kin):
        n = len(kin)
        t = np.asarray(kin.t, dtype=float)
        dt = np.diff(t, prepend=t[0] if self.t_last is None else self.t_last)
        steps = self.stream.normal(self.k, n) * np.sqrt(dt)[:, None] * self.q
        out = np.cumsum(np.concatenate([self.b_last[None, :], steps]), axis=0)[1:]
        self.k += n
        self.t_last, self.b_last = t[-1], out[-1].copy()
        return out


class _Flicker:
    """The Gauss-Markov sum of BiasInstability, each process carried across chunks
    (state x per time constant, started from its stationary distribution)."""

    def __init__(self, B, dt, seed, sid, dim):
        from scipy.signal import lfilter

        self._lfilter = lfilter
        self.sig = FLICKER_SCALE * B
        self.phi = np.exp(-dt / FLICKER_TAUS)
        self.streams = [NoiseStream(seed, (sid, i + 1), dim) for i in range(len(FLICKER_TAUS))]
        self.x = NoiseStream(seed, (sid, 0), dim).normal(0, len(FLICKER_TAUS)) * self.sig
        self.k = 0

    def next(self, kin):
        n = len(kin)
        out = np.zeros((n, self.streams[0].dim))
        for i, (phi, st) in enumerate(zip(self.phi, self.streams)):
            drive = st.normal(self.k, n) * self.sig * np.sqrt(1 - phi**2)
            y, _ = self._lfilter([1.0], [1.0, -phi], drive, axis=0, zi=(phi * self.x[i])[None, :])
            out += y
            self.x[i] = y[-1]
        self.k += n
        return out


# ---------------------------------------------------------------------------
# the catalogue

CATALOGUE = {
    "bias": Bias,
    "scale_misalignment": ScaleMisalignment,
    "installation": Installation,
    "misalignment": Misalignment,
    "g_sensitivity": GSensitivity,
    "lever_arm": LeverArm,
    "proof_mass_offsets": ProofMassOffsets,
    "accel_nonlinearity": Nonlinearity,
    "scale_asymmetry": ScaleAsymmetry,
    "temperature_drift": TemperatureDrift,
    "time_offset": TimeOffset,
    "thermal_lag": ThermalLag,
    "bias_random_walk": BiasRandomWalk,
    "bias_instability": BiasInstability,
    "white_noise": WhiteNoise,
}


def _describe_layout(params: dict, specs) -> Layout:
    """The layout whose channel count matches the fitted arrays (for describe)."""
    for v in params.values():
        a = np.asarray(v)
        if a.ndim == 1 and a.shape[0] not in (0, 3):
            n = a.shape[0]
            return Layout(n=n, el0=np.zeros(n), az0=np.zeros(n))
    return Layout()


def register_effect(cls):
    """Class decorator: put an effect class into the catalogue under its ``name``
    (the built-in effects are listed in CATALOGUE above; a new one can use this)."""
    name = cls.__dataclass_fields__["name"].default
    CATALOGUE[name] = cls
    return cls


def make_effect(name: str, sensor: str = "accel", **options) -> Effect:
    """An effect instance by catalogue name, e.g. make_effect("bias", "gyro")."""
    try:
        cls = CATALOGUE[name]
    except KeyError:
        raise ValueError(f"unknown effect {name!r}; known: {', '.join(CATALOGUE)}") from None
    if cls.sensorless:
        return cls(**options)
    return cls(sensor=sensor, **options)
