"""Rotating-table calibration on a low-grade single-axis table (docs/turntable.md).

Model (CONTRACT.md section 2): accelerometer bias b and lower-triangular K
(the instrument frame fixed by the accelerometers); gyro bias d, full G and
g-sensitivity D; per rotating cycle the lever arm s (two components
perpendicular to the table axis) and, optionally, the six proof-mass offsets
p_ij. Accelerometer i reads b_i + K_i . f(s + p_i) with
f(r) = f_ref + w x (w x r) + dw/dt x r; the gyros read d + G w + D f_ref.

Estimator: an error-state Kalman filter over the whole record. The state is
the attitude error phi (ENU, small rotation) and the parameter vector theta.
The attitude is propagated with the corrected gyros (earth rate included);
phi random-walks with the gyro white noise. Measurements, on blocks of
``block_s`` seconds (default 0.2 s):

- the block mean of the accelerometer readings against the model
  b + K (mean(R)^T g + mean([w x]^2) r_i + [mean(dw) x] r_i), in which
  mean(R) is the mean attitude over the block (exact averaging of the
  rotating gravity), mean([w x]^2) the mean centripetal operator from the
  corrected gyros, and mean(dw) = (w(end) - w(start)) / T from the gyro
  rates at the block edges (the tangential term; ``tangential=False``
  drops it);
- the direction of the table axis: mean(R) a_b = a_enu, a_b the table axis in
  body axes, estimated per cycle (two small angles: the mounting error), up to
  the table's tilt, the bearing's runout (2nd harmonic of the table angle,
  cycle-local states) and a white noise per block estimated between passes;
- where the log has them and they pass their checks, the table's angle
  (encoder) and rate channels, each with its own error states.

The passes are Gauss-Newton steps: the first an extended filter from a neutral
unit, the later ones linearised about the previous pass's estimate (the prior
then keeps its original mean, as an offset of the error state), until the last
move is below ``converge_sigma``. For constant parameters the forward filter's
final estimate and covariance are the smoothed ones; the filter's covariance
over time gives the sigma history (when each lever arm and proof-mass offset
became observable).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from calib_cli.data import CalibrationResult, Recording
from calib_cli.errors import EstimationError, InputError
from calib_cli.methods.lsq import LsqFit
from calib_cli.methods.result import build_result
from calib_cli.model.correction import correct
from calib_cli.model.effects import Layout, make_effect
from calib_cli.model.frames import attitude_to_rotation, skew
from calib_cli.model.imu_model import ImuModel, Packing, base_model
from calib_cli.model.kinematics import Kinematics, rigid_accel
from calib_cli.model.strapdown import exp_matrix as _rot
from calib_cli.model.strapdown import left_jacobian, mean_rotation, step_rotvec
from calib_cli.model.strapdown import log_matrix as _rotvec

# The fit's model is the effect catalogue's (CONTRACT.md section 2): the unit's core
# (accelerometer bias and lower-triangular K, gyro bias, full G and D) plus, per the
# options, the lever arms and the proof-mass offsets
_CORE = base_model("triad", accel_structure="lower", g_sensitivity=True)
IMU_KEYS = ("accel_bias", "accel_K", "gyro_bias", "gyro_K", "gyro_D")
# the free entries of K and of the proof-mass offsets, row-major: those their ParamSpec
# does not fix by convention (K's upper triangle: the accelerometers define the frame;
# p_ii: an accelerometer's own axis does not see its offset)
K_LOWER = [tuple(int(v) for v in ix) for ix in np.argwhere(~_CORE.spec("accel_K").fixed_mask())]
P_OFF = [tuple(int(v) for v in ix) for ix in
         np.argwhere(~make_effect("proof_mass_offsets").specs(Layout())[0].fixed_mask())]


def turntable_model(n_cycles: int, lever_arm: bool, proof_mass: bool,
                    tangential: bool) -> ImuModel:
    """The model the fit estimates, from the catalogue: the core plus the lever arms (one
    row per rotating cycle) and the proof-mass offsets where the options include them."""
    model = ImuModel(_CORE.effects, Layout(n_cycles=n_cycles))
    if lever_arm:
        model = model.with_effect(make_effect("lever_arm", tangential=tangential))
    if proof_mass:
        model = model.with_effect(make_effect("proof_mass_offsets", tangential=tangential))
    return model


# the filter's short names of the contract keys it holds one-to-one (the lever arms are
# held as two components per cycle perpendicular to its table axis)
_SHORT = {"accel_bias": "ab", "accel_K": "K", "gyro_bias": "gb", "gyro_K": "G",
          "gyro_D": "D", "proof_mass_offsets": "p"}
# the row-major flat indices of the free entries of the keys with fixed ones
_FREE = {"accel_K": [3 * i + j for i, j in K_LOWER],
         "proof_mass_offsets": [3 * i + j for i, j in P_OFF]}


def _column(L: "_Layout", key: str, flat: int) -> int:
    """Index in the filter's parameter vector of entry ``flat`` (row-major) of a contract
    key: each key's free entries (ParamSpec.fixed) are held in row-major order."""
    free = _FREE.get(key)
    return int(L.idx[_SHORT[key]][flat if free is None else free.index(flat)])


def _contract_params(par: dict, lever_arm=None) -> dict:
    """The filter's parameters (``_unpack``) under their contract keys."""
    return {"accel_bias": par["ab"], "accel_K": par["K"], "gyro_bias": par["gb"],
            "gyro_K": par["G"], "gyro_D": par["D"],
            "lever_arm": par["s"] if lever_arm is None else lever_arm,
            "proof_mass_offsets": par["P"]}


def _block_accel(K: np.ndarray, ab: np.ndarray, f: np.ndarray, C: np.ndarray,
                 r: np.ndarray) -> np.ndarray:
    """The model's accelerometer block mean (3,) in closed form, for the extended first
    pass, whose parameters change at every block (``ImuModel.predict`` costs ~0.4 ms a
    call there; tests/test_turntable.py checks the two agree): accelerometer i reads
    b_i + K_i . (f + C r_i), f the gravity part of the specific force, C the block's
    mean centripetal (+ tangential) operator, r_i = s + p_i its proof mass (m)."""
    return ab + np.einsum("ij,ij->i", K, f[None, :] + r @ C.T)


@dataclass(frozen=True)
class TurntableOptions:
    """lever_arm: "off" (no lever-arm terms), "known" (each cycle's plan
    ``lever_arm_m``), "estimate". proof_mass: "auto" (estimated; entries the
    record cannot determine are reported with sigma null and listed in
    stats.unobservable), "estimate" (the same), "off" (held at 0, reported
    with sigma null).
    tangential: include dw/dt x r. block_s: measurement block (s).
    passes: the most filter passes; from the third on they stop once the last pass moved
    no parameter by more than ``converge_sigma`` of its sigma, or the next would not
    (Gauss-Newton on the whole record: three are typical). axis_sigma: how well the table
    axis stays fixed (rad, 1-sigma per block; None: estimated from the data).
    runout_sigma: prior of the bearing's runout (rad; 0: not modelled).
    history_every: sigma history sample interval (s)."""

    lever_arm: str = "estimate"
    proof_mass: str = "auto"
    tangential: bool = True
    block_s: float = 0.2
    passes: int = 8
    # the first two passes (which only bring the linearisation point near the solution) use
    # blocks this many times longer: the block model is exact at any length, the later
    # passes' result depends on where they start only to second order (half the time)
    coarse_factor: int = 2
    converge_sigma: float = 0.1
    # the prior 1-sigma (rad) of the table bearing's twice-per-revolution rocking of the axis
    # (runout; cos and sin in each perpendicular direction, per cycle); 0: none
    runout_sigma: float = 5e-4
    # None: estimated from the axis innovations between passes (from _AXIS_START, at least
    # _axis_floor); a number: fixed
    axis_sigma: float | None = None
    # prior 1-sigma (rad) of each table axis's tilt from the plan's direction (estimated);
    # 0: the plan's axis is exact. The tilt out of the horizontal is pinned by the data
    # whatever this prior; a loose prior mainly frees the axis azimuth, which only the
    # earth rate sees, and then lets linearisation errors into the biases (docs)
    table_tilt_sigma: float = float(np.radians(0.05))
    accel_skip: float = 0.02  # rad/s^2: with tangential off, blocks accelerating faster are skipped
    history_every: float = 2.0
    noise: dict | None = None  # {"accel": (3,), "gyro": (3,)} per-sample sigma; else from data
    # the table's channels as measurements: "auto" (those the log has and that pass the
    # checks), "angle", "rate", "both", "off"
    table_encoder: str = "auto"
    rate_scale_sigma: float = 0.01  # prior of the rate channel's relative scale error
    rate_bias_sigma: float = float(np.radians(0.1))  # rad/s, prior of its offset
    encoder_sigma: float | None = None  # rad per reading; else from the channel's quantum
    encoder_opr_sigma: float = 2e-3  # rad, prior of the once-per-revolution error terms
    encoder_clock_sigma: float = 0.02  # s, prior of the encoder's clock offset to the IMU
    # relative scale error of the encoder's angle: an angle encoder's counts per revolution
    # are exact; a channel that integrates a rate or logs the setpoint fails the check below
    encoder_scale_sigma: float = 1e-5
    grade: str = "mems"  # the prior widths of GRADES
    priors: dict | None = None  # {contract key: 1-sigma, SI} overriding the grade's


# A-priori 1-sigma of each parameter group (SI) per grade of unit: weakly informative
# around a neutral unit. "mems" are the widths this fit always used (about ten times the
# catalogue's typical MEMS sizes); "navigation" is the rough-stand paper's setting (gyro
# drift 0.1 deg/h, accelerometer bias 6e-4 g, lever arms 0.1 m, proof-mass offsets 0.02 m).
GRADES = {
    "mems": {"accel_bias": 1.0, "accel_K": 0.05, "gyro_bias": 0.05, "gyro_K": 0.05,
             "gyro_D": 2e-3, "lever_arm": 0.5, "proof_mass_offsets": 0.05},
    "tactical": {"accel_bias": 0.02, "accel_K": 5e-3, "gyro_bias": float(np.radians(10 / 3600)),
                 "gyro_K": 5e-3, "gyro_D": 2e-4, "lever_arm": 0.2, "proof_mass_offsets": 0.02},
    "navigation": {"accel_bias": 6e-4 * 9.80665, "accel_K": 1e-3,
                   "gyro_bias": float(np.radians(0.1 / 3600)), "gyro_K": 1e-3, "gyro_D": 2e-5,
                   "lever_arm": 0.1, "proof_mass_offsets": 0.02},
}
PRIOR_KEYS = tuple(GRADES["mems"])
# Later passes start from the prior plus this fraction of the previous pass's data information
# (removed again exactly at the end, the pass being linear in the parameter error). Started
# from the prior alone, a direction that one cycle leaves undetermined (in cycle y the scale
# G_yy is seen only as G_yy + 0.008 G_yz, G_yz still at its 5 % prior) lets the running
# estimate wander far along it; the cycle that resolves it later transfers that wander back
# through the correlation, and any small inconsistency there came out as a 7-60 sigma error
# of one diagonal gyro scale factor (issue 14). docs/turntable.md
_START_DATA_FRACTION = 1.0


@dataclass
class _Layout:
    """Index map of the parameter vector theta."""

    n_cycles: int
    est_s: bool
    est_p: bool
    n_axes: int = 0  # table axes whose tilt from the plan's direction is estimated
    est_enc: bool = False  # the table's angle encoder: a zero per cycle, once-per-rev, clock
    est_rate: bool = False  # the table's rate channel: its scale error and offset
    idx: dict = field(default_factory=dict)
    size: int = 0

    def __post_init__(self):
        def add(name, n):
            self.idx[name] = np.arange(self.size, self.size + n)
            self.size += n
        add("ab", 3)
        add("K", 6)
        add("gb", 3)
        add("G", 9)
        add("D", 9)
        if self.est_s:
            add("s", 2 * self.n_cycles)
        if self.est_p:
            add("p", 6)
        add("u", 2 * self.n_cycles)
        add("t", 2 * self.n_axes)
        if self.est_enc:
            add("ez", self.n_cycles)
            add("eo", 2)
            add("ec", 1)
            add("es", 1)
        if self.est_rate:
            add("rk", 1)
            add("rb", 1)
            add("rz", self.n_cycles)

    @property
    def gyro(self) -> np.ndarray:
        return np.concatenate([self.idx["gb"], self.idx["G"], self.idx["D"]])


@dataclass(frozen=True)
class _Cycle:
    seg_index: int
    sl: slice
    a_enu: np.ndarray
    a_nom: np.ndarray  # table axis in body axes, nominal
    basis: np.ndarray  # (3, 2) orthonormal, perpendicular to a_nom
    rot_nom: Rotation
    s_plan: np.ndarray | None
    axis_group: int = 0  # index of the plan's table axis (cycles on one table share it)


def _perp_basis(a: np.ndarray) -> np.ndarray:
    k = int(np.argmax(np.abs(a)))
    if abs(abs(a[k]) - 1.0) < 1e-12:  # a body axis: the basis is the other two axes
        return np.eye(3)[:, [j for j in range(3) if j != k]]
    e = np.eye(3)[int(np.argmin(np.abs(a)))]
    b1 = np.cross(a, e)
    b1 /= np.linalg.norm(b1)
    b2 = np.cross(a, b1)
    return np.column_stack([b1, b2])


def _initial_lever_arm(rec: Recording, cy: "_Cycle") -> np.ndarray | None:
    """A coarse lever arm (3,), body axes, from the holds of one cycle: over whole
    revolutions at a constant rate the rotating gravity averages out and the
    accelerometers' mean is b - omega^2 s_perp (K ~ I), so regressing the hold means on
    omega^2 gives s. The first filter pass starts there: a lever arm of tens of cm
    unknown to the start would drag that pass's attitude far off. None without two
    distinct hold rates."""
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


def _third_diff_sigma(x: np.ndarray) -> np.ndarray:
    """Per-column white-noise sigma from third differences (robust: MAD)."""
    d = np.diff(x, 3, axis=0)
    mad = np.median(np.abs(d - np.median(d, axis=0)), axis=0)
    return 1.4826 * mad / np.sqrt(20.0)


def _unpack(theta: np.ndarray, L: _Layout, cycles) -> dict:
    K = np.zeros((3, 3))
    for v, (i, j) in zip(theta[L.idx["K"]], K_LOWER):
        K[i, j] = v
    P = np.zeros((3, 3))
    if L.est_p:
        for v, (i, j) in zip(theta[L.idx["p"]], P_OFF):
            P[i, j] = v
    s = np.zeros((len(cycles), 3))
    if L.est_s:
        v = theta[L.idx["s"]].reshape(-1, 2)
        for c, cy in enumerate(cycles):
            s[c] = cy.basis @ v[c]
    return {"ab": theta[L.idx["ab"]], "K": K, "gb": theta[L.idx["gb"]],
            "G": theta[L.idx["G"]].reshape(3, 3), "D": theta[L.idx["D"]].reshape(3, 3),
            "s": s, "P": P, "u": theta[L.idx["u"]].reshape(-1, 2),
            "t": theta[L.idx["t"]].reshape(-1, 2)}


@dataclass
class _Blocks:
    """Per-block quantities of one cycle, computed at the linearisation point."""

    t: np.ndarray  # (nb,) block start time
    a_mean: np.ndarray  # (nb, 3) mean accelerometer reading
    r_mean: np.ndarray  # (nb, 3, 3) mean of dR (block-start frame -> sample frame)
    r_end: np.ndarray  # (nb, 3, 3) dR at the next block's start
    cen: np.ndarray  # (nb, 3, 3) mean [w x]^2
    dw: np.ndarray  # (nb, 3) mean angular acceleration
    q: np.ndarray  # (nb, 3, 21) sum dR dw/dtheta_gyro dt
    qbar: np.ndarray  # (nb, 3, 21) block mean of the cumulative sum
    wg: np.ndarray  # (3, nb, 3, 21) mean dR^T [e_c x] cumulative sum
    wabs: np.ndarray  # (nb,) mean |w|
    w_start: np.ndarray  # (nb, 3) corrected rate at the first sample of each block
    # (nb, 3, 3, 21): d(C r)/d theta_gyro = sum_c r_c cg[:, c], C = the block's mean
    # centripetal (+ tangential) operator, r a position in body axes
    cg: np.ndarray
    wbar: np.ndarray  # (nb, 3) block mean of the corrected rates
    dw_var: np.ndarray  # (nb,) variance of the block's mean angular acceleration (corners)
    dw_raw: np.ndarray  # (nb, 3) mean angular acceleration (also with the tangential term off)
    m: int  # samples per block


def _blocks(rec: Recording, cy: _Cycle, par: dict, block_n: int, tangential: bool,
            s_known: np.ndarray | None) -> _Blocks:
    sl = cy.sl
    t = rec.time[sl]
    A = rec.accel[sl]
    W = rec.gyro[sl]
    n = (len(t) // block_n) * block_n
    nb = n // block_n
    if nb < 10:
        raise EstimationError(f"rotating segment {cy.seg_index + 1} is too short "
                              f"({len(t)} samples) for the turntable fit")
    Ginv = np.linalg.inv(par["G"])
    # the core model inverted (model/correction.py): the specific force at each proof mass
    # (row i: accelerometer i's), then the rates
    core = _contract_params(par)
    f = correct(_CORE, core, "accel", A)
    w0 = correct(_CORE, core, "gyro", W, other=f)
    # the gyros' D sees the force at the reference point: remove the proof-mass terms
    if np.any(par["P"]):
        kin0 = Kinematics(t, f, w0, np.gradient(w0, t, axis=0))
        for i in range(3):
            f[:, i] -= rigid_accel(kin0, par["P"][i])[:, i]
    w = correct(_CORE, core, "gyro", W, other=f)
    dt = np.diff(t, append=t[-1] + (t[-1] - t[-2]))
    # per-block scans over the samples of all blocks at once. Instant samples: the
    # attitude steps with the mid-interval rate from one stamp to the next, and a block's
    # accelerometer mean is the mean over its stamps. Interval means: step k is sample
    # k's own period, and the block mean is the continuous mean over its periods
    # (model/strapdown.py: step_rotvec, mean_rotation)
    interval = rec.sample_kind == "interval-mean"
    wmid = step_rotvec(w, np.ones(len(w)), rec.sample_kind)
    fmid = step_rotvec(f, np.ones(len(f)), rec.sample_kind)
    wb = w[:n].reshape(nb, block_n, 3)
    wmb = wmid[:n].reshape(nb, block_n, 3)
    fb = fmid[:n].reshape(nb, block_n, 3)
    dtb = dt[:n].reshape(nb, block_n)
    # cumulative sensitivity qc = sum_{l<m} dR_l dw_l/dtheta_gyro dt (block-start frame) of the
    # attitude at sample m, with dw/dtheta_gyro = -Ginv [I | e_j w_k | e_j f_k]; its block mean
    # (axis measurement) and mean_m dR_m^T [e_c x] qc_m (gravity measurement) enter the
    # Jacobians of the block means
    R = np.tile(np.eye(3), (nb, 1, 1))
    r_sum = np.zeros((nb, 3, 3))
    qc = np.zeros((nb, 3, 21))
    qbar = np.zeros((nb, 3, 21))
    wg = np.zeros((3, nb, 3, 21))
    ex = [skew(e) for e in np.eye(3)]
    for m in range(block_n):
        step = wmb[:, m] * dtb[:, m, None]
        # a rate change during the step moves the attitude at its end by R J_l(step) dw dt,
        # J_l = I + [step x]/2 + ... (the left Jacobian of SO(3)); R alone lags half a step
        RG = ((R @ left_jacobian(step)) * dtb[:, m, None, None]) @ Ginv
        dq = np.zeros((nb, 3, 21))
        dq[:, :, 0:3] = -RG
        dq[:, :, 3:12] = -(RG[:, :, :, None] * wmb[:, m, None, None, :]).reshape(nb, 3, 9)
        dq[:, :, 12:21] = -(RG[:, :, :, None] * fb[:, m, None, None, :]).reshape(nb, 3, 9)
        if interval:  # the mean over the sample's own period
            Rm = R @ mean_rotation(step)
            qm = qc + 0.5 * dq
        else:  # the value at the stamp
            Rm, qm = R, qc
        r_sum += Rm
        qbar += qm
        for c in range(3):
            wg[c] += np.swapaxes(Rm, 1, 2) @ (ex[c] @ qm)
        qc = qc + dq
        R = R @ Rotation.from_rotvec(step).as_matrix()
    q = qc
    # mean centripetal operator [w x]^2 = w w^T - |w|^2 I
    ww = np.einsum("bmi,bmj->bij", wb, wb) / block_n
    cen = ww - np.trace(ww, axis1=1, axis2=2)[:, None, None] * np.eye(3)
    # mean angular acceleration over the block's samples: the mean of the central
    # differences (w[i+1] - w[i-1]) / 2dt, which telescopes to the rates at the block edges
    wpad = np.concatenate([w[:1], w, w[n - 1:n] if n == len(w) else w[n:n + 1]])
    e0 = np.arange(nb) * block_n + 1  # index of the block's first sample in wpad
    e1 = e0 + block_n
    dw_raw = ((wpad[e1] + wpad[e1 - 1]) - (wpad[e0] + wpad[e0 - 1])) / (2 * dtb.sum(axis=1)[:, None])
    dwm = dw_raw if tangential else np.zeros((nb, 3))
    # Where the angular acceleration jumps (a ramp's corners) the accelerometers see the
    # value at each stamp on one side of the corner, and the central differences see the
    # mean of both: the block mean's tangential term is off by jump * (u - 1/2) / m per
    # corner, u the corner's phase between stamps (uniform): variance jump^2 / 12 / m^2,
    # 0.2 m/s^2 at 1000 deg/s^2 and 0.5 m. The jump from the second differences,
    # E sum (d2 / dt^2)^2 / 8 = jump^2 / 12, counted where it stands 4 sigma above the
    # gyro noise (rad^2/s^4)
    d2 = np.zeros(len(w))
    d2[1:-1] = np.sum((w[2:] - 2 * w[1:-1] + w[:-2]) ** 2, axis=1)
    noise2 = 6.0 * float(np.sum(_third_diff_sigma(W) ** 2))
    dt2 = float(np.median(dt)) ** 2
    jump2 = np.where(d2 > 16.0 * noise2, (d2 - noise2) / dt2**2, 0.0)
    dw_var = jump2[:n].reshape(nb, block_n).sum(axis=1) / 8.0 / block_n**2
    cg = _rigid_gyro_sensitivity(w, f, Ginv, n, block_n, dtb.sum(axis=1), tangential)
    return _Blocks(t=t[:n:block_n], a_mean=A[:n].reshape(nb, block_n, 3).mean(axis=1),
                   r_mean=r_sum / block_n, r_end=R, cen=cen, dw=dwm, q=q, cg=cg,
                   wbar=wb.mean(axis=1), dw_var=dw_var if tangential else np.zeros(nb),
                   qbar=qbar / block_n, wg=wg / block_n, dw_raw=dw_raw,
                   wabs=np.linalg.norm(wb, axis=2).mean(axis=1), m=block_n,
                   w_start=wb[:, 0].copy())


def _n_moments(u: np.ndarray, v: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Block means of u_a N (..., 3a, 3j, 21) with N = [I | e_j v^T | e_j x^T] the
    sample's dw/dtheta_gyro before the factor -G^-1: from the block means of u (...,3)
    (as mean u_a), u v^T and u x^T (..., 3, 3)."""
    sh = u.shape[:-1]
    out = np.zeros(sh + (3, 3, 21))
    for j in range(3):
        out[..., :, j, j] = u
        out[..., :, j, 3 + 3 * j:6 + 3 * j] = v
        out[..., :, j, 12 + 3 * j:15 + 3 * j] = x
    return out


def _rigid_gyro_sensitivity(w, f, Ginv, n, block_n, T, tangential):
    """Sensitivity (nb, 3, 3, 21) of the block means of the rigid-body terms to the gyro
    parameters: the centripetal and tangential accelerations at a point r are computed
    from the corrected gyros, so a gyro scale error changes them too (at 0.5 m and
    200 deg/s, 12 m/s^2 per unit of scale). d(C r)/dtheta = sum_c r_c out[:, c] with
    C r = mean(w (w.r) - r |w|^2) + dw x r; d(w (w.r) - r |w|^2)/dw = (w.r) I + w r^T
    - 2 r w^T, and dw/dtheta = -G^-1 N, N = [I | e_j w^T | e_j f^T] linear in the
    sample: every block mean comes from the block's first and second moments of w and f."""
    nb = n // block_n
    wb = w[:n].reshape(nb, block_n, 3)
    fb = f[:n].reshape(nb, block_n, 3)
    mw = wb.mean(axis=1)
    Sww = np.einsum("bma,bmk->bak", wb, wb) / block_n
    Swf = np.einsum("bma,bmk->bak", wb, fb) / block_n
    # mean w_a N (nb, 3a, 3j, 21)
    wN = _n_moments(mw, Sww, Swf)
    # mean w_a M_{a,:} summed over a, and mean w_c M (row a), mean w_a M_{c,:}
    GwN = -np.einsum("cj,bajp->bcap", Ginv, wN)  # [b, c, a, p] = mean w_a M_{c,p}
    wM = np.einsum("baap->bp", GwN)
    out = np.empty((nb, 3, 3, 21))
    for c in range(3):
        t = -np.einsum("aj,bjp->bap", Ginv, wN[:, c])  # mean w_c M
        t += GwN[:, c]  # mean w_a M_{c,:} in row a
        t[:, c, :] -= 2.0 * wM
        out[:, c] = t
    if tangential:  # mean dw/dt from the rates at the block edges, as in _blocks
        e0 = np.arange(nb) * block_n + 1
        e1 = e0 + block_n
        wpad = np.concatenate([w[:1], w, w[n - 1:n] if n == len(w) else w[n:n + 1]])
        fpad = np.concatenate([f[:1], f, f[n - 1:n] if n == len(f) else f[n:n + 1]])
        dwd = ((wpad[e1] + wpad[e1 - 1]) - (wpad[e0] + wpad[e0 - 1])) / (2 * T[:, None])
        dfd = ((fpad[e1] + fpad[e1 - 1]) - (fpad[e0] + fpad[e0 - 1])) / (2 * T[:, None])
        dN = _n_moments(np.zeros((nb, 1)), dwd[:, None, :], dfd[:, None, :])[:, 0]
        dD = -np.einsum("aj,bjp->bap", Ginv, dN)
        for c in range(3):  # dw x e_c = -[e_c x] dw
            out[:, c] -= np.einsum("ab,nbp->nap", skew(np.eye(3)[c]), dD)
    return out


_I3 = np.eye(3)
_LOW_RATE = float(np.radians(0.5))  # rad/s: blocks slower than this give the low-rate |g| figures


def _select(rec: Recording) -> list[_Cycle]:
    if rec.gyro is None:
        raise InputError("the turntable fit needs gyro data")
    if rec.layout.redundant:
        raise InputError("the turntable fit is for a triad; use `calib fit rimu` for a RIMU")
    if rec.in_counts("accel") or rec.in_counts("gyro"):
        raise InputError("the turntable fit needs data in SI units (import with a scale)")
    out = []
    axes: list = []  # distinct table axes in ENU
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
        out.append(_Cycle(i, seg.slice, a_enu, a_nom, _perp_basis(a_nom), rot,
                          None if seg.lever_arm is None else np.asarray(seg.lever_arm, float),
                          group))
    if not out:
        raise EstimationError("no rotating segments: the turntable fit needs rotation cycles")
    return out


@dataclass(frozen=True)
class _Encoder:
    """One cycle's encoder readings at the block starts: z (nb,) the angle since the
    cycle's first reading times the sign, theta (nb,) the raw angle (for the
    once-per-revolution terms), ok (nb,) usable readings; sign +-1 against the
    rotation about table_axis_enu."""

    z: np.ndarray
    theta: np.ndarray
    ok: np.ndarray
    sign: float


def _encoder_setup(rec: Recording, cycles, block_n: int, opt: TurntableOptions):
    """The encoder readings per cycle (None where unusable), their 1-sigma (rad), and
    notes. The sign against the gyros and a gross scale error are checked per cycle by
    regressing the encoder's angle on the raw gyros' integrated angle: a slope outside
    +-(1 +- 5 %) drops that cycle's encoder (never trusted blindly)."""
    mode = opt.table_encoder
    if mode not in ENCODER_MODES:
        raise InputError(f"table_encoder must be one of {', '.join(ENCODER_MODES)}, got {mode!r}")
    need = mode in ("angle", "both")
    ang = rec.table_angle
    if mode in ("off", "rate") or ang is None:
        if need:
            raise InputError(f"--table-encoder {mode}: the recording has no table_angle column")
        return None, 0.0, []
    out, notes = [], []
    interval = rec.sample_kind == "interval-mean"
    steps = []
    for cy in cycles:
        th = ang[cy.sl]
        if not np.all(np.isfinite(th)) or len(th) < 2 * block_n:
            if need:
                raise InputError(f"--table-encoder {mode}: rotating segment "
                                 f"{rec.segments[cy.seg_index].label!r} has no table angle")
            out.append(None)
            notes.append(f"{rec.segments[cy.seg_index].label}: no table angle")
            continue
        th = np.unwrap(th)
        gyro_angle = _gyro_angle(rec, cy)
        # the raw gyros' bias (up to 1 deg/s on a MEMS part) drifts their angle by radians
        # over a cycle: it is fitted alongside the slope
        tt = rec.time[cy.sl] - rec.time[cy.sl][0]
        A = np.column_stack([gyro_angle, tt])
        slope = float(np.linalg.lstsq(A, th - th[0], rcond=None)[0][0])
        if not 0.95 < abs(slope) < 1.05:
            out.append(None)
            notes.append(f"{rec.segments[cy.seg_index].label}: encoder angle / gyro angle "
                         f"= {slope:.3f}, encoder not used")
            continue
        sign = float(np.sign(slope))
        # the readings must follow the gyros over 2 s windows (rate bias and scale fitted
        # per cycle): a logged setpoint misses the table's wobble and fails here
        w = max(2, int(round(2.0 / max(float(np.median(np.diff(rec.time[cy.sl]))), 1e-9))))
        m = (len(th) - 1) // w
        if m >= 3:
            d_enc = np.diff(th[: m * w + 1: w])
            d_gyr = np.diff(gyro_angle[: m * w + 1: w])
            A = np.column_stack([d_gyr, np.ones(m)])
            res = d_enc - A @ np.linalg.lstsq(A, d_enc, rcond=None)[0]
            rms = float(np.sqrt(np.mean(res**2)))
            if rms > 5e-3:
                out.append(None)
                notes.append(f"{rec.segments[cy.seg_index].label}: the table angle does not "
                             f"follow the gyros ({rms * 1e3:.1f} mrad RMS over 2 s windows), "
                             "encoder not used")
                continue
        idx, ok = _block_starts(len(th), block_n, interval)
        out.append(_Encoder(z=sign * (th[idx] - th[0]), theta=th[idx], ok=ok, sign=sign))
        d = np.abs(np.diff(ang[cy.sl]))
        d = d[d > 1e-12]
        if len(d):
            steps.append(float(np.min(d)))
    if all(e is None for e in out):
        return None, 0.0, notes
    # one reading: the quantum's rounding noise (the smallest step the channel makes),
    # never below 20 urad
    q = min(steps) if steps else 0.0
    sig = opt.encoder_sigma if opt.encoder_sigma else max(q / np.sqrt(12.0), 2e-5)
    return out, float(sig), notes


ENCODER_MODES = ("auto", "angle", "rate", "both", "off")


def _block_starts(n_samples: int, block_n: int, interval: bool):
    """The sample index of each block's start and whether it exists: the block's first
    stamp, or for interval-mean samples (sample k spans [t_k - dt, t_k]) the stamp before
    it (the first block's start has no reading)."""
    idx = np.arange(0, (n_samples // block_n) * block_n, block_n) - (1 if interval else 0)
    return np.clip(idx, 0, n_samples - 1), idx >= 0
# rad: the integrated rate channel's reading noise, as the encoder's floor (the trapezoid
# rule's error on the profiles' kinks is far below it)
_RATE_ANGLE_FLOOR = 2e-5


def _gyro_angle(rec: Recording, cy: _Cycle) -> np.ndarray:
    """The raw gyros' angle about the plan's table axis at each stamp of a cycle since its
    first (rad), integrated as the sample kind says (model/strapdown.py step_rotvec):
    instant samples with the mid-interval rate, interval means as their own period's
    rate. A rectangle rule would lead the angle by half a sample: 35 mrad across a ramp
    from +200 to -200 deg/s at 100 Hz, far above an encoder's resolution."""
    t = rec.time[cy.sl]
    w = rec.gyro[cy.sl] @ cy.a_nom
    if rec.sample_kind == "interval-mean":  # step k spans [t_k - dt, t_k]
        steps = step_rotvec(w[1:, None], np.diff(t), rec.sample_kind)
    else:  # step k spans [t_k, t_k+1]
        steps = step_rotvec(w[:, None], np.diff(t, append=t[-1]), rec.sample_kind)[:-1]
    return np.concatenate([[0.0], np.cumsum(steps[:, 0])])


@dataclass(frozen=True)
class _RateChannel:
    """One cycle's table-rate readings integrated (trapezoid rule over the stamps) to the
    block starts: z (nb,) the angle since the cycle's first reading times the sign (rad,
    about table_axis_enu), t (nb,) its time since the first reading (s), ok (nb,) usable;
    sign +-1 against the gyros."""

    z: np.ndarray
    t: np.ndarray
    ok: np.ndarray
    sign: float

    def every(self, f: int) -> "_RateChannel":
        """Every f-th reading (longer blocks)."""
        return _RateChannel(self.z[::f], self.t[::f], self.ok[::f], self.sign)


def _rate_setup(rec: Recording, cycles, block_n: int, opt: TurntableOptions):
    """The table's rate channel per cycle (None where unusable), its per-sample 1-sigma
    (rad/s) and notes. Read as the rate at each stamp. Checked like the angle: the slope
    against the gyros' rate about the plan's axis within 1 +- 5 %, and the readings must
    follow the gyros over 2 s windows (a logged setpoint misses the wobble)."""
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
        label = rec.segments[cy.seg_index].label
        r = rt[cy.sl]
        if not np.all(np.isfinite(r)) or len(r) < 2 * block_n:
            if need:
                raise InputError(f"--table-encoder {mode}: rotating segment {label!r} has no "
                                 "table rate")
            out.append(None)
            notes.append(f"{label}: no table rate")
            continue
        g = rec.gyro[cy.sl] @ cy.a_nom
        slope = float(g @ r / max(float(g @ g), 1e-30))
        if not 0.95 < abs(slope) < 1.05:
            out.append(None)
            notes.append(f"{label}: table rate / gyro rate = {slope:.3f}, rate channel not used")
            continue
        # the block means must follow the raw gyros' (scale and offset fitted; robust
        # spread, so the ramps' timing does not count): a logged setpoint misses the
        # table's wobble, which averages out over longer windows
        n = (len(r) // block_n) * block_n
        gm = g[:n].reshape(-1, block_n).mean(axis=1)
        if interval:  # interval-mean gyros lag the stamps by half a sample
            gm = gm + 0.5 * dt * np.gradient(gm, block_n * dt)
        y = r[:n].reshape(-1, block_n).mean(axis=1)
        A = np.column_stack([gm, np.ones(len(gm))])
        res = y - A @ np.linalg.lstsq(A, y, rcond=None)[0]
        spread = 1.4826 * float(np.median(np.abs(res - np.median(res))))
        sig_r = float(np.mean(_third_diff_sigma(r[:, None])))
        sig_gyro = float(np.sqrt(np.mean(_third_diff_sigma(rec.gyro[cy.sl]) ** 2)))
        expected = np.sqrt((sig_gyro**2 + sig_r**2) / block_n)
        # (plus 0.2 deg/s: the raw unit's own g-sensitivity, bias and cross-axis terms
        # about the plan's axis reach 0.1 deg/s at the wide MEMS truths)
        if spread > 3.0 * expected + float(np.radians(0.2)):
            out.append(None)
            notes.append(f"{label}: the table rate does not follow the gyros "
                         f"({np.degrees(spread):.3f} deg/s spread per block, noise "
                         f"{np.degrees(expected):.3f}), rate channel not used")
            continue
        sign = float(np.sign(slope))
        # the readings integrated to the block starts (the encoder's stamps): as an angle
        # the channel's error is its own noise, integrated, and not the block's gyro noise,
        # which also turns the attitude (a rate row's error; docs/turntable.md)
        tt = rec.time[cy.sl] - rec.time[cy.sl][0]
        ang = np.concatenate([[0.0], np.cumsum(0.5 * (r[1:] + r[:-1]) * np.diff(tt))])
        idx, ok = _block_starts(len(r), block_n, interval)
        out.append(_RateChannel(z=sign * ang[idx], t=tt[idx], ok=ok, sign=sign))
        sig.append(sig_r)
    if all(c is None for c in out):
        return None, 0.0, notes
    return out, float(max(sig)), notes


@dataclass
class _PassOut:
    theta: np.ndarray
    P: np.ndarray
    innov: list
    nis: list
    hist_t: list
    hist_s: list
    lowrate: list
    enc_innov: list = field(default_factory=list)  # normalized encoder innovations
    rate_innov: list = field(default_factory=list)  # normalized rate-channel innovations
    # the running estimate of the sigma-history entries at the same times (issue 22: the
    # paper's fig. 4); recorded alongside hist_s, no part of the estimator
    hist_x: list = field(default_factory=list)
    # the table-axis pseudo-measurement over the second half of each cycle: mean squared
    # innovation and mean predicted variance without the axis noise (per component, rad^2)
    axis_v2: float = float("nan")
    axis_hph: float = float("nan")
    runout: list = field(default_factory=list)  # per cycle: runout amplitudes (rad)


# the free entries of K and of the proof-mass offsets as (row, column) index arrays
_K_ROWS, _K_COLS = (np.array(v) for v in zip(*K_LOWER))
_P_ROWS, _P_COLS = (np.array(v) for v in zip(*P_OFF))
_ROWS3 = np.arange(3)


def _rigid_gyro_rows(K: np.ndarray, r: np.ndarray, cg: np.ndarray) -> np.ndarray:
    """d(K_i . C r_i)/dtheta_gyro, the rigid-body terms of the accelerometer rows through
    the corrected gyros (row i at its proof mass r_i, r (3, 3)): (3, 21) from one block's
    ``_Blocks.cg`` (3, 3, 21), (nb, 3, 21) from a cycle's (nb, 3, 3, 21)."""
    if cg.ndim == 4:
        return np.einsum("ia,ic,ncap->nip", K, r, cg)
    return np.einsum("ia,ic,cap->ip", K, r, cg)


def _accel_cols(L: "_Layout", c: int) -> tuple:
    """The state columns _accel_rows writes for cycle c (per block they cost as much as
    the rows): gyro, bias, K, the cycle's lever arm, proof masses."""
    return (3 + L.gyro, 3 + L.idx["ab"], 3 + L.idx["K"],
            3 + L.idx["s"][2 * c:2 * c + 2] if L.est_s else None,
            3 + L.idx["p"] if L.est_p else None)


def _accel_rows(L: "_Layout", c: int, basis: np.ndarray, ns: int, K: np.ndarray,
                r: np.ndarray, Cw: np.ndarray, Rh: np.ndarray, r_mean: np.ndarray,
                wg: np.ndarray, KJ: np.ndarray, g_n: np.ndarray, g_sk: np.ndarray,
                cols: tuple | None = None, out: np.ndarray | None = None):
    """The accelerometer rows (3, ns) of one block's measurement Jacobian (state: the
    attitude error phi, then theta at 3 + its index) for the model b_i + K_i . (gb + C r_i)
    (``_block_accel``, ``ImuModel.predict``): K (3, 3) accelerometer K, r (3, 3) row i the
    proof mass s + p_i of accelerometer i (cycle c, lever-arm basis ``basis``), Cw the
    block's mean centripetal (+ tangential) operator, Rh the attitude at the block start,
    r_mean and wg (3, 3, 21) the block's ``_Blocks`` entries, KJ (3, 21)
    ``_rigid_gyro_rows``. Also returns the mean attitude Rbar, gravity in body axes
    gb = Rbar^T g_n and the gyro-parameter block KW. cols: ``_accel_cols(L, c)``; out:
    a zeroed (3, ns) array to write the rows into (the filter's per-block H)."""
    Rbar = Rh @ r_mean
    gb = Rbar.T @ g_n
    dfdphi = Rbar.T @ g_sk
    # force at each proof mass, row i: gravity + (centripetal + tangential) at s + p_i
    U = gb[None, :] + r @ Cw.T
    gam = Rh.T @ g_n
    Wg = gam[0] * wg[0] + gam[1] * wg[1] + gam[2] * wg[2]  # (3, 21)
    KW = K @ Wg
    # the rigid-body terms through the corrected gyros: row i at s + p_i
    KW = KW + KJ
    KCw = K @ Cw
    c_g, c_ab, c_K, c_s, c_p = cols if cols is not None else _accel_cols(L, c)
    H = np.zeros((3, ns)) if out is None else out
    H[:, c_g] = KW
    H[:, 0:3] = K @ dfdphi
    H[_ROWS3, c_ab] = 1.0
    H[_K_ROWS, c_K] = U[_K_ROWS, _K_COLS]
    if c_s is not None:
        H[:, c_s] = KCw @ basis
    if c_p is not None:
        H[_P_ROWS, c_p] = KCw[_P_ROWS, _P_COLS]
    return H, Rbar, gb, KW


def _filter_pass(rec, cycles, L: _Layout, theta_lin, prior_mean, prior_sd, opt: TurntableOptions,
                 sig_a, sig_g, block_n, s_known, record_history: bool, first: bool,
                 enc: list | None = None, sig_enc: float = 0.0,
                 rate: list | None = None, sig_rate: float = 0.0,
                 start_info: np.ndarray | None = None, tick=None,
                 axis_var: float = 1e-6) -> _PassOut:
    par = _unpack(theta_lin, L, cycles)
    par_lin = _unpack(theta_lin, L, cycles)
    if s_known is not None:
        par["s"] = s_known
    s_all = par["s"]  # (n_cycles, 3) the lever arms at the linearisation point
    model = turntable_model(len(cycles), opt.lever_arm != "off", L.est_p, opt.tangential)
    n = L.size
    # state: phi (3), theta (n), then the cycle's axis runout (cycle-local, like phi)
    th = slice(3, 3 + n)
    n_run = 4 * len(_RUNOUT_HARMONICS) if opt.runout_sigma > 0 else 0
    irun = np.arange(3 + n, 3 + n + n_run)
    # the rate channel's integrated noise since the cycle start (cycle-local, a random walk)
    irw = 3 + n + n_run
    ns = 3 + n + n_run + (1 if rate is not None else 0)
    g_n = rec.site.specific_force_enu
    g_sk = skew(g_n)
    w_e = rec.site.earth_rate_enu
    iG = 3 + L.gyro
    x = np.zeros(ns)
    # The prior keeps its original mean in every pass, but the running estimate starts at
    # theta_lin (the first pass: the neutral unit with coarse lever arms from the holds;
    # later passes: the previous pass's solution): the attitude is propagated with the
    # running estimate, and a cycle whose scale factor is tied to cross-axis terms seen
    # only in later cycles would otherwise be integrated with the neutral unit's values.
    # For the linearised problem the start mean enters the final estimate as
    # P_f P_0^-1 (m - theta_lin), added at the end.
    P = np.zeros((ns, ns))
    # start_info (later passes): the information the pass starts from, in units of the
    # prior sigma (identity = the prior); see _START_DATA_FRACTION
    if start_info is None:
        P[th, th] = np.diag(prior_sd**2)
    else:
        P[th, th] = _scaled_inv(start_info) * np.outer(prior_sd, prior_sd)
    innov, nis, hist_t, hist_s, lowrate, enc_innov = [], [], [], [], [], []
    rate_innov = []
    ax_v2, ax_hph, runout = [], [], []
    hist_idx, hist_x = [], []
    if record_history:
        if L.est_s:
            hist_idx += list(3 + L.idx["s"])
        if L.est_p:
            hist_idx += list(3 + L.idx["p"])
    next_hist = -np.inf
    for c, cy in enumerate(cycles):
        if tick is not None:
            tick()
        b = _blocks(rec, cy, par, block_n, opt.tangential, s_known)
        nb = len(b.t)
        T = b.m / rec.sample_rate
        E = _rot(-w_e * T)
        # coarse attitude: gravity from the first block, the table axis from the plan
        cur = _unpack(theta_lin + x[th], L, cycles)
        f0 = np.linalg.solve(cur["K"], b.a_mean[0] - cur["ab"])
        a_b = cy.a_nom + cy.basis @ cur["u"][c]
        a_b /= np.linalg.norm(a_b)
        rot0, _ = Rotation.align_vectors([g_n / np.linalg.norm(g_n), cy.a_enu],
                                         [f0 / np.linalg.norm(f0), a_b])
        Rh = rot0.as_matrix()
        # a new cycle: the attitude error starts fresh, uncorrelated with theta
        x[:3] = 0.0
        P[:3, :] = 0.0
        P[:, :3] = 0.0
        P[:3, :3] = np.eye(3) * np.radians(2.0) ** 2
        # the axis runout of this cycle's mounting: fresh too (the rotor's angle at the
        # cycle start is unknown without the encoder)
        x[irun] = 0.0
        P[irun, :] = 0.0
        P[:, irun] = 0.0
        P[irun, irun] = opt.runout_sigma**2
        if rate is not None:  # the integrated rate channel's walk starts at its first reading
            x[irw] = 0.0
            P[irw, :] = 0.0
            P[:, irw] = 0.0
        # the table angle since the cycle start at each block's middle, for the runout
        psi_mid = np.cumsum(b.wbar @ a_b) * T - 0.5 * (b.wbar @ a_b) * T
        sg2 = float((sig_g**2).mean())
        innov_scale = np.sqrt(b.m) / sig_a
        q_phi = block_n * sg2 * (1.0 / rec.sample_rate) ** 2
        Q_phi = _I3 * q_phi
        Cw_all = b.cen + (skew(b.dw) if opt.tangential else 0.0)
        if not first:  # linearised pass: the parameter-dependent parts are fixed per cycle
            s_lin = s_known[c] if s_known is not None else par_lin["s"][c]
            ab_lin = cy.a_nom + cy.basis @ par_lin["u"][c]
            ab_lin /= np.linalg.norm(ab_lin)
            KJ_all = _rigid_gyro_rows(par_lin["K"], s_lin[None, :] + par_lin["P"], b.cg)
            # the accelerometers' block means at the linearisation point, less gravity: the
            # catalogue's forward model on the blocks' mean kinematics
            kin_c = Kinematics(b.t, np.zeros((nb, 3)), b.wbar, b.dw, cycle=np.full(nb, c),
                               cen=b.cen)
            h_rig = model.predict(_contract_params(par_lin, s_all), kin_c,
                                  sensors=("accel",))["accel"]
        Nperp = _perp_basis(cy.a_enu).T  # (2, 3)
        acols = _accel_cols(L, c)
        skip = np.zeros(nb, bool)
        if not opt.tangential:
            fast = np.linalg.norm(b.dw_raw, axis=1) > opt.accel_skip
            skip = fast | np.roll(fast, 1) | np.roll(fast, -1)
        sA = slice(0, 3)
        ec = enc[c] if enc is not None else None
        rc = rate[c] if rate is not None else None
        if rc is not None:
            irk, irb = 3 + L.idx["rk"][0], 3 + L.idx["rb"][0]
            irz = 3 + L.idx["rz"][c]
            # the walk of the integrated channel noise per block (trapezoid rule, rad^2)
            q_rw = sig_rate**2 * block_n / rec.sample_rate**2
        if ec is not None:
            iez = 3 + L.idx["ez"][c]
            ieo = 3 + L.idx["eo"]
            iec = 3 + L.idx["ec"][0]
            ies = 3 + L.idx["es"][0]
        R_ref, psi_ref = Rh.copy(), 0.0
        for j in range(nb):
            # the first pass is an extended filter (Jacobians at the running estimate: the
            # neutral start can be far off); later passes linearise every block about the
            # previous pass's estimate, h(theta_lin) + H (theta - theta_lin), so that a pass
            # is one Gauss-Newton step of the whole record (an extended filter re-evaluated
            # from the prior at every pass keeps the bias of its early, poor linearisation,
            # which bilinear terms such as K (w x w x p) turn into tens of sigma)
            if first:
                cur = _unpack(theta_lin + x[th], L, cycles)
                s_c = s_known[c] if s_known is not None else cur["s"][c]
                a_b = cy.a_nom + cy.basis @ cur["u"][c]
                a_b /= np.linalg.norm(a_b)
            else:
                cur, s_c, a_b = par_lin, s_lin, ab_lin
            Cw = Cw_all[j]
            H = np.zeros((5, ns))
            h = np.zeros(5)
            Kc = cur["K"]
            r_c = s_c[None, :] + cur["P"]  # row i: accelerometer i's proof mass, s + p_i
            # the accelerometer rows of H (tests/test_turntable.py checks them against
            # finite differences of the catalogue model)
            _, Rbar, gb_, KW = _accel_rows(
                L, c, cy.basis, ns, Kc, r_c, Cw, Rh, b.r_mean[j], b.wg[:, j],
                _rigid_gyro_rows(Kc, r_c, b.cg[j]) if first else KJ_all[j], g_n, g_sk,
                cols=acols, out=H[:3])
            if first:
                h[:3] = _block_accel(Kc, cur["ab"], gb_, Cw, s_c[None, :] + cur["P"]) + KW @ x[iG]
            else:  # the model's rigid-body part, plus gravity through K (the model is
                # linear in the specific force; gravity in body axes follows the attitude)
                h[:3] = h_rig[j] + Kc @ gb_ + KW @ x[iG]
            # table axis fixed in ENU: Rbar a_b = a_enu (two components)
            ra = Rbar @ a_b
            Nra = -Nperp @ skew(ra)
            Hg = Nra @ Rh @ b.qbar[j]
            h[3:] = Nperp @ ra + Hg @ x[iG]
            if L.n_axes:  # the true axis: the plan's tilted by t (the table is not level)
                ti = 3 + L.idx["t"][2 * cy.axis_group:2 * cy.axis_group + 2]
                h[3:] -= cur["t"][cy.axis_group]
                H[3:, ti] = -np.eye(2)
            H[3:, iG] = Hg
            H[3:, sA] = Nra
            H[3:, 3 + L.idx["u"][2 * c:2 * c + 2]] = Nperp @ Rbar @ cy.basis
            if n_run:  # the bearing's rocking of the axis (runout), harmonics of the angle
                hp = np.multiply.outer(_RUNOUT_HARMONICS, psi_mid[j])
                cs = np.concatenate([np.cos(hp), np.sin(hp)])
                H[3, irun[:n_run // 2]] = -cs
                H[4, irun[n_run // 2:]] = -cs
                if first:
                    h[3:] += H[3:, irun] @ x[irun]
            if not first:  # the prediction linear in the parameter error about theta_lin
                h = h - H[:, iG] @ x[iG] + H[:, 3:] @ x[3:]
            z = np.concatenate([b.a_mean[j], Nperp @ cy.a_enu])
            ss = float(s_c @ s_c)
            r_extra = 4.0 * b.wabs[j] ** 2 * ss * sg2 / b.m
            if opt.tangential:
                r_extra += (sg2 / 2 / T**2 + b.dw_var[j]) * ss
            Rm = np.diag(np.concatenate([sig_a**2 / b.m + r_extra,
                                         np.full(2, axis_var)]))
            if skip[j]:  # the table accelerates and the tangential term is off: axis only
                H, h, z, Rm = H[3:], h[3:], z[3:], Rm[3:, 3:]
            n_imu = len(h)  # accelerometer (3, unless skipped) and axis (2) rows
            # the table's channels join the same update as extra rows (their noise is
            # independent of the accelerometers': one joint update is the sequential one,
            # at a third of the cost of three)
            rows = []
            use_e = ec is not None and j >= 1 and ec.ok[j]
            use_r = rc is not None and j >= 1 and j < len(rc.z) and rc.ok[j]
            if use_e or use_r:
                # the filter's angle about the table axis since the cycle's start attitude
                psi_ref += float(cy.a_enu @ _rotvec(Rh @ R_ref.T))
                R_ref = Rh
                cur_e = theta_lin + x[th]
            if use_e:
                # the table's encoder: its angle since the cycle start against the filter's
                # (the attitude about the table axis since the start attitude), with the
                # encoder's zero, once-per-revolution error and clock offset as states
                omega = float(a_b @ b.w_start[j])
                th_abs = ec.theta[j]
                He = np.zeros(ns)
                He[:3] = cy.a_enu
                He[iez] = 1.0
                He[ieo] = [np.cos(th_abs), np.sin(th_abs)]
                He[iec] = omega
                He[ies] = psi_ref
                he = (psi_ref * (1.0 + cur_e[ies - 3]) + cur_e[iez - 3]
                      + cur_e[ieo[0] - 3] * np.cos(th_abs) + cur_e[ieo[1] - 3] * np.sin(th_abs)
                      + omega * cur_e[iec - 3])
                rows.append(("enc", He, he, ec.z[j], sig_enc**2))
            if use_r:
                # the table's rate channel integrated since the cycle's first reading, the
                # same angle as the encoder's, with the channel's scale error, offset
                # (integrated: times the time), zero and integrated noise as states. As a
                # rate row its error would be the block's gyro noise about the axis, which
                # also turns the attitude: counted twice, gyro_D's sigma came out 0.8x its
                # errors (docs/turntable.md, "The rate channel")
                Hr = np.zeros(ns)
                Hr[:3] = cy.a_enu
                Hr[irk] = psi_ref
                Hr[irb] = rc.t[j]
                Hr[irz] = 1.0
                Hr[irw] = 1.0
                hr = (psi_ref * (1.0 + cur_e[irk - 3]) + cur_e[irb - 3] * rc.t[j]
                      + cur_e[irz - 3] + x[irw])
                rows.append(("rate", Hr, hr, rc.z[j], _RATE_ANGLE_FLOOR**2))
            if rows:
                H = np.vstack([H] + [r[1] for r in rows])
                h = np.concatenate([h, [r[2] for r in rows]])
                z = np.concatenate([z, [r[3] for r in rows]])
                Rm = np.diag(np.concatenate([np.diag(Rm), [r[4] for r in rows]]))
            # the state x holds phi = 0 after each reset; theta part is x[3:]
            v = z - h
            PH = P @ H.T
            S = H @ PH + Rm
            Si = np.linalg.inv(S)
            Kg = PH @ Si
            x += Kg @ v
            P -= Kg @ PH.T
            # rounding makes P drift from symmetric, and with the axis rows at 10 urad against
            # wide priors (a plan check's pass from the prior) the drift grew into negative
            # variances within 16 blocks, which had put two cross-axis entries of the plan
            # check at half the fit's sigma (issue 20): symmetric at every block
            P = 0.5 * (P + P.T)
            if not skip[j] and j >= nb // 2:  # the second half of each cycle: converged state
                innov.append(v[:3] * innov_scale)
            if j >= nb // 2:
                ax_v2.append(float(v[n_imu - 2:n_imu] @ v[n_imu - 2:n_imu]) / 2)
                ax_hph.append((float(S[n_imu - 2, n_imu - 2] + S[n_imu - 1, n_imu - 1]) / 2)
                              - axis_var)
                for q, r in enumerate(rows):  # each channel's normalized innovation
                    (enc_innov if r[0] == "enc" else rate_innov).append(
                        v[n_imu + q] / np.sqrt(S[n_imu + q, n_imu + q]))
            nis.append(float(v @ Si @ v))
            if b.wabs[j] < _LOW_RATE:
                fcorr = np.linalg.solve(Kc, b.a_mean[j] - cur["ab"])
                lowrate.append((np.linalg.norm(b.a_mean[j]), np.linalg.norm(fcorr)))
            # reset: absorb phi into the attitude
            Rh = _rot(x[:3]) @ Rh
            x[:3] = 0.0
            # propagate to the next block start
            B = Rh @ b.q[j]  # (3, 21)
            x[:3] = B @ x[iG]
            Pg = P[iG]  # (21, ns)
            BP = B @ Pg  # (3, ns)
            P[:3, :] += BP
            P[:, :3] += BP.T
            P[:3, :3] += BP[:, iG] @ B.T + Q_phi
            if rc is not None:
                P[irw, irw] += q_rw
            Rh = E @ Rh @ b.r_end[j]
            Rh = _rot(x[:3]) @ Rh
            x[:3] = 0.0
            if record_history and b.t[j] >= next_hist:
                hist_t.append(b.t[j])
                hist_s.append(np.sqrt(np.diag(P)[hist_idx]))
                hist_x.append(theta_lin[np.asarray(hist_idx, int) - 3] + x[hist_idx])
                next_hist = b.t[j] + opt.history_every
        if n_run:  # the cycle's runout amplitude per perpendicular component (rad)
            nh = len(_RUNOUT_HARMONICS)  # per direction: cos of each harmonic, then sin
            runout.append([float(np.hypot(x[irun[m * 2 * nh + q]], x[irun[m * 2 * nh + nh + q]]))
                           for m in range(2) for q in range(nh)])
    if start_info is None:
        x[th] += P[th, th] @ ((prior_mean - theta_lin) / prior_sd**2)
    else:
        # the pass is linear in the parameter error: its final information is the start's
        # plus the data's. Replace the start (mean theta_lin, information start_info) by the
        # prior (mean prior_mean, identity), in units of the prior sigma
        lam_f = _scaled_inv(P[th, th] / np.outer(prior_sd, prior_sd))
        lam = lam_f - start_info + np.eye(n)
        try:
            np.linalg.cholesky(0.5 * (lam + lam.T))
        except np.linalg.LinAlgError:  # the passes' information disagree: not linear enough
            raise _StartInfoError() from None
        rhs = lam_f @ (x[th] / prior_sd) + (prior_mean - theta_lin) / prior_sd
        x[th] = np.linalg.solve(lam, rhs) * prior_sd
        P[th, th] = _scaled_inv(lam) * np.outer(prior_sd, prior_sd)
    return _PassOut(theta_lin + x[th], P[th, th], innov, nis, hist_t, hist_s, lowrate,
                    enc_innov, rate_innov, hist_x,
                    float(np.mean(ax_v2)) if ax_v2 else float("nan"),
                    float(np.mean(ax_hph)) if ax_hph else float("nan"), runout)


class _StartInfoError(Exception):
    pass


# The table axis's per-block noise (rad): a rough stand's bearing wobbles, a simulated or a
# good table's axis does not. Fixed at a rough stand's 1 mrad, a steady axis's information
# was thrown away and the sigma it carried in was absent from the errors: gyro bias and
# g-sensitivity came out 20-30 % conservative (RMS z 0.7-0.8; issues 14, 22). So the level
# is estimated between passes from the axis innovations (mean square minus the filter's own
# predicted part), starting loose; the floor keeps the update well conditioned.
_AXIS_START = 1e-3
# The runout's harmonics of the table angle: an oval bearing race rocks the axis twice per
# revolution, which at any one rate looks like g-sensitivity (gravity turns once per
# revolution in the body: D g in the table frame holds the 0th and 2nd harmonics); left as
# white noise a 0.1 mrad runout made gyro_D overconfident (RMS z 1.4). The first harmonic
# is not a state: in the axis measurement it repeats the cycle's mounting error u and a gyro
# bias across the axis, and it took up 0.2-0.5 mrad of them on records without runout.
_RUNOUT_HARMONICS = np.array([2.0])
_AXIS_FLOOR = 1e-5
_AXIS_CAP = 2e-2
# The floor is at most this fraction of the attitude's random walk over one block (the gyro
# noise). An axis noise assumed far above that walk while the true one is below it makes
# every sigma the axis carries ~1.4x the errors, whatever the level (the axis noise and
# the walk then share the attitude's error about equally, and the first is absent): at
# navigation grade (walk 0.22 urad a block) the 10 urad floor gave gyro bias RMS z 0.74,
# 1 urad 0.76, 0.1 urad 1.04 (issue 22). A MEMS gyro's walk (39 urad) keeps 10 urad.
_AXIS_FLOOR_WALK = 0.5


def _axis_floor(sig_g: np.ndarray, block_n: int, fs: float) -> float:
    """The floor (rad per block) of the estimated axis noise."""
    walk = float(np.sqrt(block_n * np.mean(np.square(sig_g)))) / fs
    return min(_AXIS_FLOOR, _AXIS_FLOOR_WALK * walk) if walk > 0 else _AXIS_FLOOR


def _axis_noise(out: "_PassOut", axis_var: float, floor: float = _AXIS_FLOOR) -> tuple[float, bool]:
    """The next pass's axis noise variance (rad^2) and whether it moved by more than
    20 % in sigma (the passes then go on)."""
    est = out.axis_v2 - out.axis_hph
    if not np.isfinite(est):
        return axis_var, False
    new = float(np.clip(est, floor**2, _AXIS_CAP**2))
    return new, abs(np.log(new / axis_var)) > 2 * np.log(1.2)


def _scaled_inv(A: np.ndarray) -> np.ndarray:
    """Inverse of a symmetric positive-definite matrix, symmetrised."""
    Ai = np.linalg.inv(0.5 * (A + A.T))
    return 0.5 * (Ai + Ai.T)


def fit_turntable(rec: Recording, options: TurntableOptions = TurntableOptions(),
                  progress=None, _at: dict | None = None) -> CalibrationResult:
    """Fit the turntable model to a raw recording with rotating segments.

    progress: optional callback ``progress(done, total)``, called once per cycle
    and filter pass (a retry with widened noise extends the total).
    _at: see ``covariance_at`` (experiment design)."""
    opt = options
    if opt.lever_arm not in ("off", "known", "estimate"):
        raise InputError(f"lever_arm must be off, known or estimate, got {opt.lever_arm!r}")
    if opt.proof_mass not in ("auto", "off", "estimate"):
        raise InputError(f"proof_mass must be auto, off or estimate, got {opt.proof_mass!r}")
    if opt.proof_mass == "estimate" and opt.lever_arm == "off":
        raise InputError("proof-mass offsets need the lever-arm terms (--lever-arm known|estimate)")
    est_p = opt.proof_mass == "estimate" or (opt.proof_mass == "auto" and opt.lever_arm != "off")
    cycles = _select(rec)
    nc = len(cycles)
    s_known = None
    if opt.lever_arm == "known":
        missing = [rec.segments[cy.seg_index].label for cy in cycles if cy.s_plan is None]
        if missing:
            raise InputError(f"--lever-arm known needs lever_arm_m in the plan for every rotating "
                             f"segment; missing: {', '.join(missing)}")
        s_known = np.array([cy.s_plan for cy in cycles])
    elif opt.lever_arm == "off":
        s_known = np.zeros((nc, 3))
    n_axes = 1 + max(cy.axis_group for cy in cycles) if opt.table_tilt_sigma > 0 else 0
    fs = rec.sample_rate
    block_n = max(1, int(round(opt.block_s * fs)))
    enc, sig_enc, enc_notes = _encoder_setup(rec, cycles, block_n, opt)
    shortest = min(cy.sl.stop - cy.sl.start for cy in cycles)
    coarse_n = block_n * max(1, int(opt.coarse_factor))
    if shortest < 50 * coarse_n:
        coarse_n = block_n
    enc_coarse = _encoder_setup(rec, cycles, coarse_n, opt)[0] if coarse_n != block_n else enc
    rate, sig_rate, rate_notes = _rate_setup(rec, cycles, block_n, opt)
    rate_coarse = _rate_setup(rec, cycles, coarse_n, opt)[0] if coarse_n != block_n else rate
    enc_notes += rate_notes
    L = _Layout(nc, opt.lever_arm == "estimate", est_p, n_axes, est_enc=enc is not None,
                est_rate=rate is not None)
    on = np.concatenate([np.arange(rec.segments[cy.seg_index].start,
                                   rec.segments[cy.seg_index].stop) for cy in cycles])
    if opt.noise is not None:
        sig_a = np.asarray(opt.noise["accel"], float) * np.ones(3)
        sig_g = np.asarray(opt.noise["gyro"], float) * np.ones(3)
    else:
        sig_a = _third_diff_sigma(rec.accel[on])
        sig_g = _third_diff_sigma(rec.gyro[on])
    # prior: wide around a neutral unit (and the plan's lever arms where given)
    mean = np.zeros(L.size)
    sd = np.zeros(L.size)
    mean[L.idx["K"][[0, 2, 5]]] = 1.0
    mean[L.idx["G"][[0, 4, 8]]] = 1.0
    if opt.grade not in GRADES:
        raise InputError(f"grade must be one of {', '.join(GRADES)}, got {opt.grade!r}")
    width = dict(GRADES[opt.grade])
    for k, v in (opt.priors or {}).items():
        if k not in width:
            raise InputError(f"unknown prior key {k!r}; expected one of {', '.join(PRIOR_KEYS)}")
        if not (np.isfinite(v) and v > 0):
            raise InputError(f"prior {k} must be a positive number, got {v!r}")
        width[k] = float(v)
    sd[L.idx["ab"]] = width["accel_bias"]
    sd[L.idx["K"]] = width["accel_K"]
    sd[L.idx["gb"]] = width["gyro_bias"]
    sd[L.idx["G"]] = width["gyro_K"]
    sd[L.idx["D"]] = width["gyro_D"]
    if L.est_s:
        for c, cy in enumerate(cycles):
            if cy.s_plan is not None:
                mean[L.idx["s"][2 * c:2 * c + 2]] = cy.basis.T @ cy.s_plan
        sd[L.idx["s"]] = width["lever_arm"]
    if L.est_p:
        sd[L.idx["p"]] = width["proof_mass_offsets"]
    sd[L.idx["u"]] = np.radians(3.0)
    sd[L.idx["t"]] = opt.table_tilt_sigma
    if L.est_enc:
        sd[L.idx["ez"]] = 0.1  # the encoder's zero against the coarse start attitude
        sd[L.idx["eo"]] = opt.encoder_opr_sigma
        sd[L.idx["ec"]] = opt.encoder_clock_sigma
        sd[L.idx["es"]] = opt.encoder_scale_sigma
    if L.est_rate:
        sd[L.idx["rk"]] = opt.rate_scale_sigma
        sd[L.idx["rb"]] = opt.rate_bias_sigma
        sd[L.idx["rz"]] = 0.1  # the integrated channel's zero against the coarse start attitude
    if _at is not None:  # experiment design: one linearised pass at the given unit
        return _pass_at(rec, cycles, L, mean, sd, opt, sig_a, sig_g, block_n, s_known, enc,
                        sig_enc, rate, sig_rate, width, _at)
    # a model that does not explain the data (e.g. lever arms ignored) leaves accelerometer
    # residuals far above the noise and can drag the attitude off; the fit then restarts with
    # the measurement noise widened to the residual level (stats.accel_noise_inflation), so
    # the covariance says how little such a fit is worth
    # where the first pass starts (its running estimate; the prior keeps its mean): the
    # neutral unit with coarse lever arms from the holds (a housing measurement in the
    # plan stays the prior mean)
    start = mean.copy()
    if L.est_s:
        for c, cy in enumerate(cycles):
            s0 = _initial_lever_arm(rec, cy)
            if s0 is not None:
                start[L.idx["s"][2 * c:2 * c + 2]] = cy.basis.T @ s0
    # convergence is judged on the reported parameters: nuisance states such as the
    # encoder's zero per cycle re-absorb the coarse start attitude at every pass
    rep_idx = np.concatenate([L.idx[k] for k in ("ab", "K", "gb", "G", "D", "s", "p")
                              if k in L.idx])
    inflation = 1.0
    enc_inflation = 1.0
    tick = None
    if progress is not None:
        steps = [0, min(3, max(1, opt.passes)) * nc]  # three passes are typical

        def tick():
            steps[0] += 1
            if steps[0] > steps[1]:  # one more pass, or a retry
                steps[1] += nc
            progress(steps[0], steps[1])

    if opt.axis_sigma is not None and not (np.isfinite(opt.axis_sigma) and opt.axis_sigma > 0):
        raise InputError(f"axis_sigma must be > 0 rad, got {opt.axis_sigma!r}")
    if not (np.isfinite(opt.runout_sigma) and opt.runout_sigma >= 0):
        raise InputError(f"runout_sigma must be >= 0 rad, got {opt.runout_sigma!r}")
    for _attempt in range(6):
        theta = start.copy()
        info_start = None
        hist = None
        n_passes, moved = 0, np.inf
        axis_var = (opt.axis_sigma if opt.axis_sigma is not None else _AXIS_START) ** 2
        axis_moved = False
        diverged = False
        bad_channels = []
        for k in range(max(1, opt.passes)):
            coarse = k < min(2, opt.passes - 1)
            bn = coarse_n if coarse else block_n
            kw = dict(record_history=k == 0, enc=enc_coarse if coarse else enc,
                      sig_enc=sig_enc * enc_inflation, rate=rate_coarse if coarse else rate,
                      sig_rate=sig_rate, tick=tick, axis_var=axis_var)
            used_axis_var = axis_var
            try:
                out = _filter_pass(rec, cycles, L, theta, mean, sd, opt, sig_a * inflation,
                                   sig_g, bn, s_known, first=k == 0,
                                   start_info=info_start, **kw)
            except _StartInfoError:  # fall back to a pass started from the prior alone
                kw["record_history"] = False
                try:
                    out = _filter_pass(rec, cycles, L, theta, mean, sd, opt, sig_a * inflation,
                                       sig_g, bn, s_known, first=False, **kw)
                except np.linalg.LinAlgError:
                    out = None
            except np.linalg.LinAlgError:  # NaN in the state: the filter diverged
                out = None
            if out is None or not np.all(np.isfinite(out.theta)):
                diverged = True
                break
            # a table channel far from its model already in this pass (normalized innovation
            # RMS above 5, against about 1 for a real encoder even in the first pass): a
            # logged setpoint that passed the checks, which would drag the passes off
            for name, v in (("encoder", out.enc_innov), ("rate channel", out.rate_innov)):
                r_ = float(np.sqrt(np.mean(np.square(v)))) if v else 0.0
                if r_ > 5.0:
                    bad_channels.append((name, r_))
            if bad_channels:
                break
            if hist is None:  # the sigma history is the first pass's (it starts from the prior)
                hist = (out.hist_t, out.hist_s, out.hist_x)
            out.hist_t, out.hist_s, out.hist_x = hist
            # the largest move of any parameter since the pass before, in its sigma (the
            # first pass, an extended filter from the neutral unit, is not compared)
            prev_move = moved
            moved = (float(np.max(np.abs(out.theta - theta)[rep_idx]
                                  / np.sqrt(np.diag(out.P))[rep_idx])) if k >= 1 else np.inf)
            n_passes = k + 1
            theta = out.theta
            # converged: this pass moved less than the tolerance, or the next pass would,
            # extrapolating the last two moves at a linear rate (Gauss-Newton with exact
            # Jacobians converges faster: 35 -> 1.4 -> 0.004 sigma on a wide MEMS truth)
            if k >= 2 and not axis_moved and (moved < opt.converge_sigma
                                              or moved**2 / prev_move < opt.converge_sigma):
                break
            if opt.axis_sigma is None and k >= 0:
                axis_var, axis_moved = _axis_noise(out, axis_var,
                                                   _axis_floor(sig_g, block_n, fs))
            # the next pass starts from the prior plus this pass's data information
            lam = _scaled_inv(out.P / np.outer(sd, sd))
            info_start = np.eye(L.size) + _START_DATA_FRACTION * (lam - np.eye(L.size))
        if bad_channels and not diverged:
            for name, r_ in bad_channels:
                enc_notes.append(f"{name} not used: normalized innovation RMS {r_:.3g} in "
                                 f"pass {k + 1}")
                if name == "encoder":
                    enc = enc_coarse = None
                else:
                    rate = rate_coarse = None
            continue
        if diverged and (enc is not None or rate is not None):
            # e.g. a logged setpoint that passed the checks: its readings miss the table's
            # wobble, which at navigation-grade gyro noise drags the first pass off
            enc_notes.append("table channels not used: the filter diverged with them")
            enc = enc_coarse = rate = rate_coarse = None
            continue
        if diverged:
            inflation *= 10.0
            continue
        r = float(np.sqrt(np.mean(np.square(out.innov)))) if out.innov else 1.0
        r_enc = float(np.sqrt(np.mean(np.square(out.enc_innov)))) if out.enc_innov else 1.0
        if enc is not None and not (r_enc < 1.5 and r < 1.3):
            # readings the model does not explain (a scale error of a setpoint log, a slipping
            # coupling), or accelerometers that disagree with them: the encoder is dropped and
            # the fit rerun from the IMU alone (it is never trusted blindly)
            enc_notes.append(f"encoder not used: normalized innovation RMS {r_enc:.1f} "
                             f"(encoder), {r:.2f} (accelerometers) with it")
            enc = enc_coarse = None
            continue
        r_rate = (float(np.sqrt(np.mean(np.square(out.rate_innov)))) if out.rate_innov
                  else 1.0)
        if rate is not None and not (r_rate < 1.5 and r < 1.3):
            enc_notes.append(f"rate channel not used: normalized innovation RMS {r_rate:.1f} "
                             f"(rate), {r:.2f} (accelerometers) with it")
            rate = rate_coarse = None
            continue
        if np.all(np.isfinite(out.theta)) and r < 1.3:
            break
        # widen step by step (a diverged attempt's residuals overstate the mismatch)
        inflation *= min(max(r, 2.0), 10.0) if np.isfinite(r) else 10.0
    if diverged or not np.all(np.isfinite(out.theta)):
        raise EstimationError("the turntable filter diverged")
    res = _result(rec, cycles, L, out, opt, s_known, sig_a * inflation, sig_g, block_n,
                  inflation, sd, width)
    res.stats["accel_clipped_samples"] = _clipped(rec, cycles)
    # the table axis's per-block noise the final pass used (estimated unless given)
    res.stats["table_axis_noise_mrad"] = float(np.sqrt(used_axis_var) * 1e3)
    res.stats["table_axis_noise_mode"] = "given" if opt.axis_sigma is not None else "estimated"
    # per cycle, the axis's rocking (runout) the final pass found, urad: the amplitude of the
    # harmonics of _RUNOUT_HARMONICS in each of the two perpendicular directions
    res.stats["table_axis_runout_urad"] = [[a * 1e6 for a in r] for r in out.runout]
    # the Gauss-Newton passes: how many ran, and the last pass's largest move in sigma
    res.stats["filter_passes"] = n_passes
    res.stats["filter_last_move_sigma"] = float(moved) if np.isfinite(moved) else None
    res.stats["table_encoder"] = _encoder_stats(enc, L, out, sig_enc * enc_inflation,
                                                enc_inflation, enc_notes, rate, sig_rate)
    # issue 22: the paper's check positions (static segments the fit did not use)
    from calib_cli.methods.check_positions import check_positions

    res.stats["check_positions"] = check_positions(rec, res)
    return res


def covariance_at(rec: Recording, options: TurntableOptions, at: dict) -> CalibrationResult:
    """The fit's covariance at a known unit (``calib plan check``, docs/plan.md): the same
    set-up as ``fit_turntable`` (prior, noise, table channels, nuisance states), then the
    fit's final pass: a linearised filter pass about ``at`` (contract keys: accel_bias,
    accel_K, gyro_bias, gyro_K, gyro_D, lever_arm (n_cycles, 3), proof_mass_offsets;
    missing: the prior mean) started, as the fit's later passes are, from the prior plus
    the data information of a cheap pass (the first tenth of each cycle, blocks 4 times
    longer), which is removed again exactly at the end. The pass is linear in the parameter error, so its
    covariance is the one the fit's Gauss-Newton passes end with on a record of that unit;
    on a noise-free record of it nothing else is needed. ``options.noise`` must be given.
    The result's params are ``at``'s; its sigma, covariance and stats.unobservable the
    fit's."""
    from dataclasses import replace

    # coarse_factor 1: the coarse passes' table channels are not needed
    return fit_turntable(rec, replace(options, coarse_factor=1), _at=at)


def _pass_at(rec, cycles, L, mean, sd, opt, sig_a, sig_g, block_n, s_known, enc, sig_enc,
             rate, sig_rate, width, at: dict, pre_factor: int = 4,
             pre_span: float = 0.1) -> CalibrationResult:
    theta = mean.copy()
    keys = list(IMU_KEYS) + (["proof_mass_offsets"] if L.est_p else [])
    for key in keys:
        if at.get(key) is None:
            continue
        v = np.asarray(at[key], float).ravel()
        for flat in _FREE.get(key, range(len(v))):
            theta[_column(L, key, flat)] = v[flat]
    if L.est_s and at.get("lever_arm") is not None:
        s = np.asarray(at["lever_arm"], float).reshape(-1, 3)
        for c, cy in enumerate(cycles):
            theta[L.idx["s"][2 * c:2 * c + 2]] = cy.basis.T @ s[c]
    # the axis noise a fit estimates on a steady axis (its floor), unless given. Not the
    # fit's gyro-walk floor (_axis_floor): that stiff an axis does not bear this pass's
    # linearisation at zero mounting error (at navigation grade, 0.11 urad, a 0.3 deg
    # mounting error put gyro_K at 0.05-0.2 of the fit's sigma, equal within 0.2 % without
    # one; issue 22)
    axis_var = (opt.axis_sigma if opt.axis_sigma is not None else _AXIS_FLOOR) ** 2
    kw = dict(record_history=False, first=False, axis_var=axis_var)
    # Started from the prior alone, the pass's covariance depended on the record's noise
    # draw (issue 20: at the 0.01 mrad axis floor one gyro_K cross-axis entry came out 0.03
    # to 1.0 of the fit's sigma, record by record): the table axis and the rate channel
    # shrink some directions of the prior-wide covariance by many orders of magnitude, and
    # its rounding left it with negative eigenvalues (-2e-6 in units of the prior). The
    # fit's final pass starts from the prior plus the previous pass's data information
    # (_START_DATA_FRACTION), removes it exactly at the end and checks the result is
    # positive definite; so does this one. Its start information comes from a cheap pass
    # over the first ``pre_span`` of each cycle (at least 20 blocks) on blocks up to
    # ``pre_factor`` times longer, with the same table channels: while the pass is linear
    # any start gives the same covariance (measured: within 1e-6 of a start from a pass
    # over the whole record at the fit's blocks). Fallbacks: that start, then the prior.
    from dataclasses import replace

    shortest = min(cy.sl.stop - cy.sl.start for cy in cycles)
    f0 = max(1, int(pre_factor))
    while f0 > 1 and shortest * pre_span < 20 * f0 * block_n:
        f0 //= 2
    out = None
    for f, span in dict.fromkeys(((f0, pre_span), (1, 1.0))):
        pre_cycles = []
        for cy in cycles:
            n = cy.sl.stop - cy.sl.start
            k = max(20 * f * block_n, int(span * n))
            pre_cycles.append(cy if k >= n else replace(cy, sl=slice(cy.sl.start, cy.sl.start + k)))
        # the same channels over the longer blocks: every f-th reading of each
        e_pre = enc if enc is None or f == 1 else [
            None if e is None else _Encoder(e.z[::f], e.theta[::f], e.ok[::f], e.sign)
            for e in enc]
        r_pre = rate if rate is None or f == 1 else [
            None if r is None else r.every(f) for r in rate]
        with np.errstate(invalid="ignore"):  # its innovation statistics are not used
            pre = _filter_pass(rec, pre_cycles, L, theta, mean, sd, opt, sig_a, sig_g,
                               f * block_n, s_known, enc=e_pre, sig_enc=sig_enc, rate=r_pre,
                               sig_rate=sig_rate, **kw)
        lam = _scaled_inv(pre.P / np.outer(sd, sd))
        info = np.eye(L.size) + _START_DATA_FRACTION * (lam - np.eye(L.size))
        try:
            out = _filter_pass(rec, cycles, L, theta, mean, sd, opt, sig_a, sig_g, block_n,
                               s_known, enc=enc, sig_enc=sig_enc, rate=rate, sig_rate=sig_rate,
                               start_info=info, **kw)
            break
        except _StartInfoError:
            continue
    if out is None:
        out = _filter_pass(rec, cycles, L, theta, mean, sd, opt, sig_a, sig_g, block_n, s_known,
                           enc=enc, sig_enc=sig_enc, rate=rate, sig_rate=sig_rate, **kw)
    out.theta = theta
    res = _result(rec, cycles, L, out, opt, s_known, sig_a, sig_g, block_n, 1.0, sd, width)
    res.stats["table_encoder"] = _encoder_stats(enc, L, out, sig_enc, 1.0, [], rate, sig_rate)
    res.stats["table_axis_noise_mrad"] = float(np.sqrt(axis_var) * 1e3)
    return res


def _clipped(rec: Recording, cycles) -> list[int]:
    """Per accelerometer axis, samples of the cycles that sit exactly at the axis's extreme
    value: a saturated sensor repeats its full-scale reading, noise never does (the
    centripetal and tangential terms at a large lever arm can exceed the range)."""
    A = np.concatenate([rec.accel[cy.sl] for cy in cycles])
    out = []
    for i in range(A.shape[1]):
        col = A[:, i]
        n = int(np.sum(col == col.max())) + int(np.sum(col == col.min()))
        out.append(n if n > 10 else 0)
    return out


def _encoder_stats(enc, L, out, sig_enc, inflation, notes, rate=None, sig_rate=0.0) -> dict:
    """What the table's channels contributed (stats.table_encoder): mode, cycles used, the
    estimated once-per-revolution amplitude and clock offset with sigma, the reading noise
    used; for the rate channel its scale error and offset with sigma."""
    P = out.P
    rate_part = {}
    if rate is not None:
        ik, ib = L.idx["rk"][0], L.idx["rb"][0]
        rate_part = {
            "rate_cycles_used": [r is not None for r in rate],
            "rate_scale_error": float(out.theta[ik]),
            "rate_scale_error_sigma": float(np.sqrt(P[ik, ik])),
            "rate_offset_dps": float(np.degrees(out.theta[ib])),
            "rate_offset_sigma_dps": float(np.degrees(np.sqrt(P[ib, ib]))),
            "rate_reading_sigma_dps": float(np.degrees(sig_rate)),
            "rate_normalized_innovation_rms": float(np.sqrt(np.mean(np.square(out.rate_innov))))
            if out.rate_innov else None}
    if enc is None:
        return {"mode": "rate" if rate is not None else "off", **rate_part, "notes": notes}
    eo = out.theta[L.idx["eo"]]
    ec = float(out.theta[L.idx["ec"][0]])
    return {"mode": "both" if rate is not None else "angle", **rate_part,
            "cycles_used": [e is not None for e in enc],
            "sign": [None if e is None else e.sign for e in enc],
            "once_per_rev_mrad": [float(v) * 1e3 for v in eo],
            "once_per_rev_sigma_mrad": [float(np.sqrt(P[i, i])) * 1e3 for i in L.idx["eo"]],
            "clock_offset_ms": ec * 1e3,
            "clock_offset_sigma_ms": float(np.sqrt(P[L.idx["ec"][0], L.idx["ec"][0]])) * 1e3,
            "reading_sigma_urad": sig_enc * 1e6, "noise_inflation": float(inflation),
            "normalized_innovation_rms": float(np.sqrt(np.mean(np.square(out.enc_innov))))
            if out.enc_innov else None, "notes": notes}


def _tilts(cycles, L, par, P, prior: float) -> list:
    """Each table axis's estimated tilt from the plan's direction: the two small
    angles along the ENU unit vectors perpendicular to it (mrad, with sigma; None
    where the data did not determine it: sigma above half the prior, e.g. the
    azimuth of a horizontal axis, which only the earth rate sees)."""
    out = []
    for g in range(L.n_axes):
        cy = next(c for c in cycles if c.axis_group == g)
        sd = [float(np.sqrt(P[i, i])) for i in L.idx["t"][2 * g:2 * g + 2]]
        out.append({"plan_axis_enu": [float(v) for v in cy.a_enu],
                    "perpendicular_enu": [[float(v) for v in r] for r in _perp_basis(cy.a_enu).T],
                    "tilt_mrad": [float(v) * 1e3 for v in par["t"][g]],
                    "sigma_mrad": [None if v > 0.5 * prior else v * 1e3 for v in sd]})
    return out


def _result(rec, cycles, L, out: _PassOut, opt, s_known, sig_a, sig_g, block_n, inflation,
            prior_sd_vec, prior_widths):
    theta, P = out.theta, out.P
    par = _unpack(theta, L, cycles)
    nc = len(cycles)
    model = turntable_model(nc, opt.lever_arm != "off", L.est_p, opt.tangential)
    # the reported entries: the catalogue's free entries of each estimated key (a lever
    # arm's component along its cycle's table axis is not estimated: fixed at 0)
    keys = list(IMU_KEYS) + (["lever_arm"] if L.est_s else []) + (
        ["proof_mass_offsets"] if L.est_p else [])
    masks = []
    for k in keys:
        if k == "lever_arm":
            masks.append(np.array([np.abs(cy.basis).sum(axis=1) > 0 for cy in cycles]))
        else:
            masks.append(~model.spec(k).fixed_mask())
    packing = Packing(tuple(model.spec(k) for k in keys), tuple(masks))
    # each reported entry as a row over the filter's parameter vector
    T = np.zeros((packing.size, L.size))
    for q, (key, flat) in enumerate(packing.labels()):
        if key == "lever_arm":
            c, e = divmod(flat, 3)
            T[q, L.idx["s"][2 * c:2 * c + 2]] = cycles[c].basis[e]
        else:
            T[q, _column(L, key, flat)] = 1.0
    cov = T @ P @ T.T
    # an entry the data did not determine (sigma still above half its prior): sigma null
    prior_sd = np.sqrt(np.diag(T @ np.diag(prior_sd_vec**2) @ T.T))
    unobs = np.sqrt(np.clip(np.diag(cov), 0, None)) > 0.5 * prior_sd
    cov[unobs, :] = np.nan
    cov[:, unobs] = np.nan
    fit = LsqFit(theta=T @ theta, cov=cov, unobservable=unobs, residuals=np.zeros(0),
                 chi2=float("nan"), dof=0, nfev=0)
    base = model.neutral_params()
    pm_fixed = []
    extra = {}
    if opt.lever_arm == "known":
        extra["lever_arm"] = s_known
    if not L.est_p:  # the key is always present (CONTRACT.md section 7): 0, sigma null
        extra["proof_mass_offsets"] = np.zeros((3, 3))
        pm_fixed = [f"proof_mass_offsets[{i},{j}]" for i, j in P_OFF]
    innov = np.array(out.innov)
    lowrate = np.array(out.lowrate) if out.lowrate else np.zeros((0, 2))
    g = rec.site.gravity
    a_b = []
    for c, cy in enumerate(cycles):
        v = cy.a_nom + cy.basis @ par["u"][c]
        a_b.append(v / np.linalg.norm(v))
    u_sd = np.sqrt(np.diag(P)[L.idx["u"]]).reshape(-1, 2)
    stats = {
        "accel_residual_rms": float(np.sqrt(np.mean(innov**2)) * np.mean(sig_a)) if len(innov)
        else None,
        "normalized_innovation_rms": float(np.sqrt(np.mean(innov**2))) if len(innov) else None,
        "nis_mean": float(np.mean(out.nis)) if out.nis else None,
        "g_error_rms_before": float(np.sqrt(np.mean((lowrate[:, 0] - g) ** 2))) if len(lowrate)
        else None,
        "g_error_rms_after": float(np.sqrt(np.mean((lowrate[:, 1] - g) ** 2))) if len(lowrate)
        else None,
        "n_cycles": len(cycles),
        "cycles": [rec.segments[cy.seg_index].label for cy in cycles],
        "lever_arm_mode": opt.lever_arm, "proof_mass_mode": opt.proof_mass,
        "tangential": bool(opt.tangential), "block_s": block_n / rec.sample_rate,
        "passes": int(opt.passes), "grade": opt.grade,
        "prior_sigma": {k: float(v) for k, v in prior_widths.items()},
        "accel_noise_inflation": float(inflation),
        "noise_accel": [float(v) for v in sig_a], "noise_gyro": [float(v) for v in sig_g],
        "table_axis_body": [[float(v) for v in a] for a in a_b],
        "table_axis_body_sigma_rad": [[float(v) for v in r] for r in u_sd],
        "table_axis_tilt_mrad": _tilts(cycles, L, par, P, opt.table_tilt_sigma),
        "g_error_floor": float(np.sqrt(np.mean(sig_a**2) / block_n)),
        "g_error_note": f"|mean f| - g over blocks of {block_n / rec.sample_rate:g} s where the "
                        "table is at rest",
    }
    tables = {}
    if out.hist_t:
        labels = []
        if L.est_s:
            for c, cy in enumerate(cycles):
                for m in range(2):
                    e = int(np.argmax(np.abs(cy.basis[:, m])))
                    tag = "xyz"[e] if abs(abs(cy.basis[e, m]) - 1) < 1e-12 else f"b{m + 1}"
                    labels.append(f"lever_arm[{c}].{tag}")
        if L.est_p:
            labels += [f"p_{'xyz'[i]}{'xyz'[j]}" for i, j in P_OFF]
        tables["sigma_history_time"] = np.array(out.hist_t)
        tables["sigma_history"] = np.array(out.hist_s)
        tables["sigma_history_labels"] = labels
        if out.hist_x:  # the running estimate alongside (same entries, same units)
            tables["estimate_history"] = np.array(out.hist_x)
    res = build_result("turntable", model, packing, fit, base, rec.units, stats,
                       serial=rec.serial, tables=tables, extra_unobservable=pm_fixed)
    for k, v in extra.items():  # reported, not estimated
        res.params[k] = np.asarray(v, float)
        res.sigma[k] = (np.zeros((nc, 3)) if k == "lever_arm"
                        else np.where(np.eye(3) > 0, 0.0, np.nan))
        res.units[k] = "m"
    order = [k for k in (*IMU_KEYS, "lever_arm", "proof_mass_offsets") if k in res.params]
    for d in (res.params, res.sigma, res.units):
        items = {k: d.pop(k) for k in order}
        d.update(items)
    return res
