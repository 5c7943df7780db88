"""What the rotating-table fit knows before it starts: the cycles of a recording, the
model and its parameter vector with the priors, the noise levels, the table's channels
(checked) and where the iterations start."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from calib_cli.data import Recording
from calib_cli.errors import EstimationError, InputError
from calib_cli.methods.noise import difference_sigma
from calib_cli.methods.turntable.options import ENCODER_MODES, GRADES, PRIOR_KEYS, TurntableOptions
from calib_cli.model.effects import Layout, make_effect
from calib_cli.model.frames import attitude_to_rotation
from calib_cli.model.imu_model import ImuModel, Packing, base_model
from calib_cli.model.strapdown import cumulative_integral, step_rotvec

# The fit's model is the effect catalogue's (CONTRACT.md section 2): the unit's core
# (accelerometer bias and lower-triangular K, gyro bias, full G and D) plus, per the
# options, the lever arms and the proof-mass offsets, plus any --with effects
CORE = base_model("triad", accel_structure="lower", g_sensitivity=True)
IMU_KEYS = ("accel_bias", "accel_K", "gyro_bias", "gyro_K", "gyro_D")
# effects that act between the IMU and the table's channels, not on a sensor: the
# estimator holds them as states of the channels' rows (rows.py)
CHANNEL_EFFECTS = ("time_offset",)


def turntable_model(n_cycles: int, lever_arm: bool, proof_mass: bool, tangential: bool,
                    effects=(), g_sensitivity: bool = True, structure: str = "full") -> ImuModel:
    """The model the fit estimates, from the catalogue: the core (without the gyros'
    g-sensitivity where ``g_sensitivity`` is False: the diagnosis's base model; with
    diagonal scale factors where ``structure`` is "diagonal") plus the lever arms (one row
    per rotating cycle), the proof-mass offsets and ``effects`` [(name, sensor)]."""
    core = [e for e in CORE.effects if g_sensitivity or e.name != "g_sensitivity"]
    if structure == "diagonal":
        core = [make_effect("scale_misalignment", e.sensor, structure="diagonal")
                if e.name == "scale_misalignment" else e for e in core]
    model = ImuModel(tuple(core), Layout(n_cycles=n_cycles))
    if lever_arm:
        model = model.with_effect(make_effect("lever_arm", tangential=tangential))
    if proof_mass:
        model = model.with_effect(make_effect("proof_mass_offsets", tangential=tangential))
    for name, sensor in effects:
        if name in CHANNEL_EFFECTS:
            model = model.with_effect(make_effect(name, sensor or "accel"))
            continue
        if model.has(name, sensor or None) and name != "misalignment":
            continue
        opts = {"structure": "lower" if sensor == "accel" else "full"} \
            if name == "misalignment" else {}
        model = model.with_effect(make_effect(name, sensor or "accel", **opts))
    return model


@dataclass(frozen=True)
class Cycle:
    """One rotating segment (or a static position the fit uses). sl: its samples; a_enu:
    the plan's table axis (ENU, unit); a_nom: that axis in body axes at the nominal
    mounting; basis (3, 2): two unit vectors perpendicular to a_nom (the lever arm's and
    the mounting error's axes);
    rot_nom: the plan's attitude; s_plan: the plan's lever arm (m) or None; axis_group:
    which of the plan's distinct table axes; mount_sigma (rad): the mounting's prior
    1-sigma, ``mount_stated``: given by the plan (information) or the fit's default."""

    seg_index: int
    label: str
    sl: slice
    a_enu: np.ndarray
    a_nom: np.ndarray
    basis: np.ndarray
    rot_nom: Rotation
    s_plan: np.ndarray | None
    axis_group: int
    mount_sigma: float
    mount_stated: bool
    model_index: int = -1  # its row of the lever arm (-1: a static position, none)
    static: bool = False  # a static position of known attitude (see select_cycles)


def axis_in_body(cy, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cycle cy's table axis in body axes at mounting u (2,): (a_b (3,), d a_b / d u (3, 2)),
    the plan's a_nom turned by u along the basis and normalised (with a stiff axis, 10
    urad, the plain basis as the derivative was wrong by u^2 ~ 1e-5 and Gauss-Newton
    stalled)."""
    a_u = cy.a_nom + cy.basis @ u
    n = float(np.linalg.norm(a_u))
    a_b = a_u / n
    return a_b, (np.eye(3) - np.outer(a_b, a_b)) @ cy.basis / n


def perp_basis(a: np.ndarray) -> np.ndarray:
    """(3, 2): two orthonormal vectors perpendicular to the unit vector a (the other two
    body axes where a is one)."""
    k = int(np.argmax(np.abs(a)))
    if abs(abs(a[k]) - 1.0) < 1e-12:
        return np.eye(3)[:, [j for j in range(3) if j != k]]
    e = np.eye(3)[int(np.argmin(np.abs(a)))]
    b1 = np.cross(a, e)
    b1 /= np.linalg.norm(b1)
    return np.column_stack([b1, np.cross(a, b1)])


def select_cycles(rec: Recording, opt: TurntableOptions) -> list[Cycle]:
    """The rotating segments of a recording (InputError for a recording the method cannot
    take, EstimationError without a rotating segment)."""
    if rec.gyro is None:
        raise InputError("the turntable fit needs gyro data")
    if rec.layout.redundant:
        raise InputError("the turntable fit is for a triad; use `calib fit rimu` for a RIMU")
    if rec.in_counts("accel") or rec.in_counts("gyro"):
        raise InputError("the turntable fit needs data in SI units (import with a scale)")
    out: list[Cycle] = []
    axes: list = []
    for i, seg in enumerate(rec.segments):
        if seg.kind != "rotating":
            continue
        if seg.table_axis_enu is None or seg.attitude is None:
            raise InputError(f"rotating segment {seg.label!r} needs table_axis_enu and "
                             "attitude_deg (the nominal mounting) in the plan")
        rot = attitude_to_rotation(seg.attitude)
        a_enu = np.asarray(seg.table_axis_enu, float) / np.linalg.norm(seg.table_axis_enu)
        a_nom = rot.inv().apply(a_enu)
        k = int(np.argmax(np.abs(a_nom)))
        if abs(abs(a_nom[k]) - 1) < 1e-9:
            a_nom = np.sign(a_nom[k]) * np.eye(3)[k]
        group = next((g for g, a in enumerate(axes) if np.allclose(a, a_enu, atol=1e-9)), None)
        if group is None:
            axes.append(a_enu)
            group = len(axes) - 1
        stated = seg.attitude_sigma is not None and np.isfinite(seg.attitude_sigma)
        msig = float(seg.attitude_sigma) if stated else float(opt.mount_sigma)
        out.append(Cycle(i, seg.label, seg.slice, a_enu, a_nom, perp_basis(a_nom), rot,
                         None if seg.lever_arm is None else np.asarray(seg.lever_arm, float),
                         group, max(msig, 1e-9), stated, model_index=len(out)))
    if not out:
        raise EstimationError("no rotating segments: the turntable fit needs rotation cycles")
    if not gravity_reference(out):
        out += static_positions(rec)
    return out


# a table axis within this angle of the vertical turns nothing of gravity in body axes
VERTICAL = float(np.radians(10.0))
# rad: a static position's attitude where the plan gives no attitude_sigma_deg (the
# contract's example of a fixture, 0.05 deg; it also covers the mrad between the housing's
# axes, which the plan's attitudes are in, and the instrument frame of a lower-triangular
# K: held at 1e-5 rad, a unit with 2e-3 upper entries misfit its static positions at 3x
# the noise of 0.3 mg accelerometers)
STATIC_ATTITUDE_SD = float(np.radians(0.05))


def vertical(cy: Cycle) -> bool:
    """The cycle's table axis within VERTICAL of the vertical."""
    return abs(float(cy.a_enu[2])) > np.cos(VERTICAL)


def gravity_reference(cycles) -> bool:
    """Whether the rotating cycles give the accelerometers a gravity reference: a table
    axis away from the vertical turns gravity through the body axes (both signs), and a
    stated mounting fixes its direction on a vertical one. Without either, a common tilt of
    the mountings, the accelerometers' K and biases and the gyros' misalignment turn
    together at nearly equal cost (methods/turntable/result.py: what is then reported)."""
    return any(cy.mount_stated or not vertical(cy) for cy in cycles if not cy.static)


def static_positions(rec: Recording) -> list[Cycle]:
    """The static segments of known attitude as cycles of a table that does not turn
    (their attitude the plan's, to its attitude_sigma_deg or STATIC_ATTITUDE_SD)."""
    out = []
    for i, seg in enumerate(rec.segments):
        if seg.kind != "static" or seg.attitude is None:
            continue
        rot = attitude_to_rotation(seg.attitude)
        up = np.array([0.0, 0.0, 1.0])
        a_nom = rot.inv().apply(up)
        sd = float(seg.attitude_sigma) if seg.attitude_sigma is not None and \
            np.isfinite(seg.attitude_sigma) else STATIC_ATTITUDE_SD
        out.append(Cycle(i, seg.label, seg.slice, up, a_nom, perp_basis(a_nom), rot, None, -1,
                         max(sd, 1e-9), True, model_index=-1, static=True))
    return out


def white_noise(x: np.ndarray) -> np.ndarray:
    """Per-column white-noise sigma from third differences (robust: MAD), the table's
    corners and ramps removed by the differencing (methods/noise.py)."""
    return difference_sigma(x, 3, robust="mad")


# ---------------------------------------------------------------------------
# the parameter vector


@dataclass
class ParamMap:
    """The estimator's parameter vector theta: the model's free entries (contract keys;
    each cycle's lever arm as two components in its ``basis``), then the nuisance
    states. ``idx[group]``: the indices of a group ("model" per contract key, "lever_arm"
    (n_cycles, 2), "mount" (n_cycles, 2), "tilt" (n_axes, 2), "runout" (n_cycles, 4),
    "enc_zero" (n_cycles,), "enc_opr" (2,), "enc_scale" (1,), "rate_scale", "rate_bias"
    (1,), "rate_zero" (n_cycles,), "time_offset" (1,)). mean, sd: the prior; informative:
    the prior is information (a stated mounting, the channels' physics), not a default
    width (the observability test leaves the others out)."""

    model: ImuModel
    cycles: list
    packing: Packing  # the model's free entries without the lever arm
    keys: list  # (key, flat) per packing column
    idx: dict = field(default_factory=dict)
    size: int = 0
    mean: np.ndarray = None
    sd: np.ndarray = None
    informative: np.ndarray = None

    def add(self, name: str, shape) -> np.ndarray:
        n = int(np.prod(shape))
        self.idx[name] = np.arange(self.size, self.size + n).reshape(shape)
        self.size += n
        return self.idx[name]

    def has(self, name: str) -> bool:
        return name in self.idx and self.idx[name].size > 0

    def model_index(self, key: str, flat: int) -> int:
        return int(self.model_cols[(key, int(flat))])

    # The lever arm is held in units of the square of the gyro scale about the cycle's
    # axis, u = s / gamma^2 with gamma = a^T G a: the centripetal term the accelerometers
    # see is K [w x]^2 s with w = G^-1 W, i.e. K u (W about a)^2, linear in u, and the
    # tangential term gamma K (a x u) dW/dt is linear in gamma. In (s, G) the two made a
    # curved valley (s ~ gamma^2 along it) that Gauss-Newton crept along at 3 sigma a pass
    # on a vertical axis, where nothing else fixes the gyro scale about it.

    def rotating(self) -> list:
        """The rotating cycles, in the lever arm's row order."""
        return [cy for cy in self.cycles if not cy.static]

    def gyro_scale(self, theta: np.ndarray, c: int) -> tuple[float, np.ndarray, np.ndarray]:
        """(gamma, its derivative by the gyro_K entries (9,), their theta indices) of the
        c-th rotating cycle (the lever arm's row c)."""
        a = self.rotating()[c].a_nom
        ks = [k for k in range(9) if ("gyro_K", k) in self.model_cols]  # (diagonal G: 3)
        gi = np.array([self.model_cols[("gyro_K", k)] for k in ks])
        G = np.zeros(9)
        G[ks] = theta[gi]
        return float(a @ G.reshape(3, 3) @ a), np.outer(a, a).ravel()[ks], gi

    def lever(self, theta: np.ndarray, c: int) -> np.ndarray:
        """Cycle c's lever arm s (3,), body axes, m."""
        gam = self.gyro_scale(theta, c)[0]
        return gam**2 * (self.rotating()[c].basis @ theta[self.idx["lever_arm"][c]])

    def lever_jacobian(self, theta: np.ndarray, c: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(d s / d u (3, 2), d s / d gyro_K (3, 9), the gyro_K theta indices) of cycle c."""
        gam, dg, gi = self.gyro_scale(theta, c)
        basis = self.rotating()[c].basis
        sb = basis @ theta[self.idx["lever_arm"][c]]
        return gam**2 * basis, 2.0 * gam * np.outer(sb, dg), gi

    def params(self, theta: np.ndarray, lever_known: np.ndarray | None = None) -> dict:
        """The contract parameters of the model at theta (lever arms in body axes)."""
        base = self.model.neutral_params()
        p = self.packing.unpack(theta[self.idx["packing"]], base)
        if "lever_arm" in base:
            n = len(self.rotating())
            if self.has("lever_arm"):
                p["lever_arm"] = np.array([self.lever(theta, c) for c in range(n)])
            else:
                p["lever_arm"] = (np.zeros((n, 3)) if lever_known is None
                                  else np.asarray(lever_known, float))
        return p

    def set_params(self, theta: np.ndarray, params: dict) -> None:
        """Write contract parameters (those given) into theta."""
        for q, (key, flat) in enumerate(self.keys):
            if params.get(key) is not None:
                theta[self.idx["packing"][q]] = np.asarray(params[key], float).ravel()[flat]
        if self.has("lever_arm") and params.get("lever_arm") is not None:
            s = np.asarray(params["lever_arm"], float).reshape(-1, 3)
            for c, cy in enumerate(self.rotating()):
                gam = self.gyro_scale(theta, c)[0]
                theta[self.idx["lever_arm"][c]] = cy.basis.T @ s[c] / gam**2


def param_map(model: ImuModel, cycles: list, opt: TurntableOptions, n_axes: int,
              enc: bool, rate: bool) -> ParamMap:
    """The parameter vector, its prior (mean, sd) and which priors are information."""
    keys = [s.key for s in model.specs() if s.key not in ("lever_arm", "time_offset")]
    packing = Packing.for_model(model, keys=keys)
    pm = ParamMap(model, cycles, packing, packing.labels())
    nc = len(cycles)
    rotating = [cy for cy in cycles if not cy.static]
    pm.add("packing", (packing.size,))
    pm.model_cols = {kf: int(pm.idx["packing"][q]) for q, kf in enumerate(pm.keys)}
    if model.has("lever_arm") and opt.lever_arm == "estimate":
        pm.add("lever_arm", (len(rotating), 2))
    pm.add("mount", (nc, 2))
    pm.add("tilt", (n_axes, 2))
    pm.add("runout", (nc, 4) if opt.runout_sigma > 0 else (nc, 0))
    if enc:
        pm.add("enc_zero", (nc,))
        pm.add("enc_opr", (2,))
        pm.add("enc_scale", (1,))
    if rate:
        pm.add("rate_scale", (1,))
        pm.add("rate_bias", (1,))
        pm.add("rate_zero", (nc,))
    if model.has("time_offset"):
        pm.add("time_offset", (1,))
    pm.mean = np.zeros(pm.size)
    pm.sd = np.zeros(pm.size)
    pm.informative = np.zeros(pm.size, bool)
    width = prior_widths(opt)
    for q, (key, flat) in enumerate(pm.keys):
        spec = model.spec(key)
        i = pm.idx["packing"][q]
        pm.mean[i] = spec.neutral().ravel()[flat]
        pm.sd[i] = width.get(key, 10.0 * spec.typical)
    if pm.has("lever_arm"):
        for cy in rotating:
            if cy.s_plan is not None:
                pm.mean[pm.idx["lever_arm"][cy.model_index]] = cy.basis.T @ cy.s_plan
        pm.sd[pm.idx["lever_arm"]] = width["lever_arm"]
    for c, cy in enumerate(cycles):  # (a static position's entries take part in no row)
        pm.sd[pm.idx["mount"][c]] = cy.mount_sigma
        pm.informative[pm.idx["mount"][c]] = cy.mount_stated
    pm.sd[pm.idx["tilt"]] = max(opt.table_tilt_sigma, 1e-9)
    pm.informative[pm.idx["tilt"]] = True  # the table's levelling: a physical bound
    if opt.runout_sigma > 0:
        pm.sd[pm.idx["runout"]] = opt.runout_sigma
        pm.informative[pm.idx["runout"]] = True
    if enc:
        pm.sd[pm.idx["enc_zero"]] = 1.0  # the reading's zero against the start attitude
        pm.sd[pm.idx["enc_opr"]] = opt.encoder_opr_sigma
        pm.sd[pm.idx["enc_scale"]] = opt.encoder_scale_sigma
        pm.informative[pm.idx["enc_opr"]] = pm.informative[pm.idx["enc_scale"]] = True
    if rate:
        pm.sd[pm.idx["rate_scale"]] = opt.rate_scale_sigma
        pm.sd[pm.idx["rate_bias"]] = opt.rate_bias_sigma
        pm.sd[pm.idx["rate_zero"]] = 1.0
        pm.informative[pm.idx["rate_scale"]] = pm.informative[pm.idx["rate_bias"]] = True
    if pm.has("time_offset"):
        pm.sd[pm.idx["time_offset"]] = 0.1
    return pm


def prior_widths(opt: TurntableOptions) -> dict:
    """The prior 1-sigma per contract key (the grade's, overridden by ``priors``)."""
    if opt.grade not in GRADES:
        raise InputError(f"grade must be one of {', '.join(GRADES)}, got {opt.grade!r}")
    width = dict(GRADES[opt.grade])
    for k, v in (opt.priors or {}).items():
        if k not in width:
            raise InputError(f"unknown prior key {k!r}; expected one of {', '.join(PRIOR_KEYS)}")
        if not (np.isfinite(v) and v > 0):
            raise InputError(f"prior {k} must be a positive number, got {v!r}")
        width[k] = float(v)
    return width


# ---------------------------------------------------------------------------
# the table's channels


@dataclass(frozen=True)
class AngleChannel:
    """One cycle's table-angle readings at the block starts: z (nb,) the angle since the
    cycle's first reading times ``sign`` (rad, about table_axis_enu), theta (nb,) the raw
    angle (the once-per-revolution terms), ok (nb,) usable readings."""

    z: np.ndarray
    theta: np.ndarray
    ok: np.ndarray
    sign: float


@dataclass(frozen=True)
class RateChannel:
    """One cycle's table-rate readings integrated (trapezoid rule) to the block starts:
    z (nb,) the angle since the first reading times ``sign`` (rad), t (nb,) the time
    since the first reading (s), ok (nb,) usable."""

    z: np.ndarray
    t: np.ndarray
    ok: np.ndarray
    sign: float


def block_starts(n_samples: int, block_n: int, interval: bool):
    """The sample index of each block's start and whether it exists: the block's first
    stamp, or for interval-mean samples (sample k spans [t_k - dt, t_k]) the stamp before
    it (the first block's start has no reading)."""
    idx = np.arange(0, (n_samples // block_n) * block_n, block_n) - (1 if interval else 0)
    return np.clip(idx, 0, n_samples - 1), idx >= 0


def gyro_angle(rec: Recording, cy: Cycle) -> np.ndarray:
    """The raw gyros' angle about the plan's table axis at each stamp of a cycle since its
    first (rad), integrated as the sample kind says (model/strapdown.py)."""
    t = rec.time[cy.sl]
    w = rec.gyro[cy.sl] @ cy.a_nom
    if rec.sample_kind == "interval-mean":  # step k spans [t_k - dt, t_k]
        steps = step_rotvec(w[1:, None], np.diff(t), rec.sample_kind)
    else:
        steps = step_rotvec(w[:, None], np.diff(t, append=t[-1]), rec.sample_kind)[:-1]
    return np.concatenate([[0.0], np.cumsum(steps[:, 0])])


def _follow_check(th: np.ndarray, ga: np.ndarray, t: np.ndarray) -> tuple[float, float]:
    """(slope, RMS over 2 s windows) of a channel's angle against the raw gyros' angle:
    the slope with the gyros' bias fitted alongside, then the windows' increments with a
    scale and offset fitted (a logged setpoint misses the table's wobble)."""
    tt = t - t[0]
    A = np.column_stack([ga, tt])
    slope = float(np.linalg.lstsq(A, th - th[0], rcond=None)[0][0])
    dt = max(float(np.median(np.diff(t))), 1e-9)
    w = max(2, int(round(2.0 / dt)))
    m = (len(th) - 1) // w
    if m < 3:
        return slope, 0.0
    d_enc = np.diff(th[: m * w + 1: w])
    d_gyr = np.diff(ga[: m * w + 1: w])
    A = np.column_stack([d_gyr, np.ones(m)])
    res = d_enc - A @ np.linalg.lstsq(A, d_enc, rcond=None)[0]
    return slope, float(np.sqrt(np.mean(res**2)))


def angle_noise(th: np.ndarray, ga: np.ndarray) -> float:
    """The angle channel's white reading noise (rad per reading) from the high-frequency
    content of its difference to the raw gyros' angle (whose own noise is a random walk
    of one sample's rate noise per step, far smaller per step): third differences, MAD;
    a quantised channel whose steps stay below the noise gives its quantum / sqrt(12)."""
    d = th - ga
    sig = float(difference_sigma(d[:, None], 3, robust="auto")[0])
    steps = np.abs(np.diff(th))
    steps = steps[steps > 1e-12]
    q = float(np.min(steps)) if len(steps) else 0.0
    return max(sig, q / np.sqrt(12.0))


def angle_channels(rec: Recording, cycles, block_n: int, opt: TurntableOptions):
    """The angle readings per cycle (None where unusable), the white reading noise
    estimated from the readings (rad; or ``encoder_sigma``) and notes. Checked per cycle
    against the raw gyros' angle: a slope outside 1 +- 5 % (a wrong unit or sign is the
    sign), or readings that do not follow the gyros over 2 s windows, drop the cycle's
    readings (never trusted blindly)."""
    mode = opt.table_encoder
    if mode not in ENCODER_MODES:
        raise InputError(f"table_encoder must be one of {', '.join(ENCODER_MODES)}, got {mode!r}")
    need = mode in ("angle", "both")
    ang = rec.table_angle
    if mode in ("off", "rate") or ang is None:
        if need:
            raise InputError(f"--table-encoder {mode}: the recording has no table_angle column")
        return None, 0.0, []
    out, notes, sig = [], [], []
    interval = rec.sample_kind == "interval-mean"
    for cy in cycles:
        th = ang[cy.sl]
        if not np.all(np.isfinite(th)) or len(th) < 2 * block_n:
            if need:
                raise InputError(f"--table-encoder {mode}: rotating segment {cy.label!r} has no "
                                 "table angle")
            out.append(None)
            notes.append(f"{cy.label}: no table angle")
            continue
        th = np.unwrap(th)
        ga = gyro_angle(rec, cy)
        slope, rms = _follow_check(th, ga, rec.time[cy.sl])
        if not 0.95 < abs(slope) < 1.05:
            out.append(None)
            notes.append(f"{cy.label}: table angle / gyro angle = {slope:.3f}, angle channel "
                         "not used")
            continue
        sign = float(np.sign(slope))
        s_hf = angle_noise(sign * th, ga)
        if rms > 5e-3 + 3.0 * s_hf:
            out.append(None)
            notes.append(f"{cy.label}: the table angle does not follow the gyros "
                         f"({rms * 1e3:.1f} mrad RMS over 2 s windows), angle channel not used")
            continue
        idx, ok = block_starts(len(th), block_n, interval)
        out.append(AngleChannel(z=sign * (th[idx] - th[0]), theta=th[idx], ok=ok, sign=sign))
        sig.append(s_hf)
    if all(e is None for e in out):
        return None, 0.0, notes
    s = opt.encoder_sigma if opt.encoder_sigma else max(float(np.median(sig)), 1e-7)
    return out, float(s), notes


# rad: the integrated rate channel's reading noise floor (the trapezoid rule's error on the
# profiles' kinks is far below it)
RATE_ANGLE_FLOOR = 2e-5


def rate_channels(rec: Recording, cycles, block_n: int, opt: TurntableOptions):
    """The table's rate channel per cycle (None where unusable), its per-sample 1-sigma
    (rad/s) and notes. Checked like the angle: the slope against the gyros' rate about the
    plan's axis within 1 +- 5 %, and the block means must follow the gyros'."""
    mode = opt.table_encoder
    need = mode in ("rate", "both")
    rt = rec.table_rate
    if mode not in ("auto", "rate", "both") or rt is None:
        if need:
            raise InputError(f"--table-encoder {mode}: the recording has no table_rate column")
        return None, 0.0, []
    out, notes, sig = [], [], []
    dt = float(np.median(np.diff(rec.time)))
    interval = rec.sample_kind == "interval-mean"
    for cy in cycles:
        r = rt[cy.sl]
        if not np.all(np.isfinite(r)) or len(r) < 2 * block_n:
            if need:
                raise InputError(f"--table-encoder {mode}: rotating segment {cy.label!r} has no "
                                 "table rate")
            out.append(None)
            notes.append(f"{cy.label}: no table rate")
            continue
        g = rec.gyro[cy.sl] @ cy.a_nom
        slope = float(g @ r / max(float(g @ g), 1e-30))
        if not 0.95 < abs(slope) < 1.05:
            out.append(None)
            notes.append(f"{cy.label}: table rate / gyro rate = {slope:.3f}, rate channel not used")
            continue
        n = (len(r) // block_n) * block_n
        gm = g[:n].reshape(-1, block_n).mean(axis=1)
        if interval:  # interval-mean gyros lag the stamps by half a sample
            gm = gm + 0.5 * dt * np.gradient(gm, block_n * dt)
        y = r[:n].reshape(-1, block_n).mean(axis=1)
        A = np.column_stack([gm, np.ones(len(gm))])
        res = y - A @ np.linalg.lstsq(A, y, rcond=None)[0]
        spread = 1.4826 * float(np.median(np.abs(res - np.median(res))))
        sig_r = float(white_noise(r[:, None])[0])
        sig_gyro = float(np.sqrt(np.mean(white_noise(rec.gyro[cy.sl]) ** 2)))
        expected = np.sqrt((sig_gyro**2 + sig_r**2) / block_n)
        # plus 0.2 deg/s: the raw unit's own g-sensitivity, bias and cross-axis terms about
        # the plan's axis reach 0.1 deg/s at the wide MEMS truths
        if spread > 3.0 * expected + float(np.radians(0.2)):
            out.append(None)
            notes.append(f"{cy.label}: the table rate does not follow the gyros "
                         f"({np.degrees(spread):.3f} deg/s spread per block, noise "
                         f"{np.degrees(expected):.3f}), rate channel not used")
            continue
        sign = float(np.sign(slope))
        tt = rec.time[cy.sl] - rec.time[cy.sl][0]
        ang = cumulative_integral(r, tt)  # the cubic: exact for an oscillation
        idx, ok = block_starts(len(r), block_n, interval)
        out.append(RateChannel(z=sign * ang[idx], t=tt[idx], ok=ok, sign=sign))
        sig.append(sig_r)
    if all(c is None for c in out):
        return None, 0.0, notes
    return out, float(max(sig)), notes


# ---------------------------------------------------------------------------
# where the iterations start


def initial_lever_arm(rec: Recording, cy: Cycle) -> np.ndarray | None:
    """A coarse lever arm (3,), body axes, from the holds of one cycle: over whole
    revolutions at a constant rate the rotating gravity averages out and the
    accelerometers' mean is b - omega^2 s_perp (K ~ I), so regressing the hold means on
    omega^2 gives s. None without two distinct hold rates."""
    fs = rec.sample_rate
    W = rec.gyro[cy.sl]
    A = rec.accel[cy.sl]
    om = W @ cy.a_nom
    m = max(1, int(round(fs)))
    nw = len(om) // m
    if nw < 4:
        return None
    wm = om[: nw * m].reshape(nw, m)
    mean, sd = wm.mean(axis=1), wm.std(axis=1)
    hold = (np.abs(mean) > 0.5) & (sd < 0.01 * np.abs(mean) + 2e-3)
    rows, rates = [], []
    k = 0
    while k < nw:
        if not hold[k]:
            k += 1
            continue
        e = k
        while e + 1 < nw and hold[e + 1] and abs(mean[e + 1] - mean[k]) < 0.02 * abs(mean[k]):
            e += 1
        rate = float(np.mean(mean[k:e + 1]))
        n_rev = int(abs(rate) * (e + 1 - k) / (2 * np.pi))
        if n_rev >= 1:
            n = int(round(n_rev * 2 * np.pi / abs(rate) * fs))
            rows.append(A[k * m:k * m + n].mean(axis=0))
            rates.append(rate**2)
        k = e + 1
    if len(rates) < 2 or np.ptp(rates) < 0.5:
        return None
    X = np.column_stack([np.ones(len(rates)), rates])
    coef = np.linalg.lstsq(X, np.array(rows), rcond=None)[0]
    s = -coef[1]
    return s - cy.a_nom * (s @ cy.a_nom)


def gyro_mounting(rec: Recording, cy: Cycle) -> np.ndarray | None:
    """The mounting u (2,) at which the table axis in body axes is the direction the gyros
    turn about: the principal axis of the cycle's 1 s gyro means (their second moment, so
    the turns in both senses add). Off the truth by the gyros' misalignment (mrad) where
    the plan's attitude may be degrees off. None for a cycle that barely turns."""
    fs = rec.sample_rate
    W = rec.gyro[cy.sl]
    m = max(1, int(round(fs)))
    nw = len(W) // m
    if nw < 4:
        return None
    wm = W[: nw * m].reshape(nw, m, 3).mean(axis=1)
    w, V = np.linalg.eigh(wm.T @ wm / nw)
    if w[-1] < (np.radians(5.0)) ** 2 or w[-2] > 0.1 * w[-1]:  # slow, or not one axis
        return None
    a = V[:, -1] * np.sign(V[:, -1] @ cy.a_nom)
    if a @ cy.a_nom < np.cos(np.radians(30.0)):  # far from the plan's: a wrong plan
        return None
    return cy.basis.T @ (a / (a @ cy.a_nom))


def start_attitude(cy: Cycle, f0: np.ndarray, g_enu: np.ndarray,
                   u: np.ndarray | None = None) -> np.ndarray:
    """The attitude (3, 3, body -> ENU) a cycle starts from: the plan's mounting turned
    about the table axis so that the specific force f0 (body axes) seen at the start points
    up (the table's angle at the segment start is unknown); on a vertical axis, where
    gravity does not fix that angle, the plan's attitude tilted to the start's mounting u
    (its table axis in body axes onto the table's)."""
    R = cy.rot_nom.as_matrix()
    if u is not None and np.any(u != 0.0) and vertical(cy):
        a_b = axis_in_body(cy, u)[0]
        return R @ Rotation.align_vectors([cy.a_nom], [a_b])[0].as_matrix()
    a = cy.a_enu
    v = R @ (f0 / max(np.linalg.norm(f0), 1e-12))
    gh = g_enu / np.linalg.norm(g_enu)
    vp, gp = v - a * (v @ a), gh - a * (gh @ a)
    if np.linalg.norm(vp) < 0.05 or np.linalg.norm(gp) < 0.05:
        return R
    ang = float(np.arctan2(a @ np.cross(vp, gp), vp @ gp))
    return Rotation.from_rotvec(a * ang).as_matrix() @ R
