"""The rotating-table fit's result: the contract's parameters with their covariance, what
the record cannot determine, and the statistics of the fit, its noise and the table."""

from __future__ import annotations

import numpy as np

from calib_cli.errors import EstimationError
from calib_cli.methods.lsq import LsqFit
from calib_cli.methods.result import build_result
from calib_cli.methods.turntable import estimator as es
from calib_cli.methods.turntable.options import GRADES
from calib_cli.methods.turntable.rows import ACC
from calib_cli.methods.turntable.setup import (
    IMU_KEYS,
    VERTICAL,
    axis_in_body,
    gravity_reference,
    perp_basis,
    prior_widths,
    vertical,
)
from calib_cli.model.imu_model import Packing

# An entry is determined by the record when its sigma from the data alone (and the priors
# that are information: a mounting the plan states, the table's levelling, the channels'
# physics) is below this fraction of its prior width; the mounting's default width and
# the grade's widths count as no information (CONTRACT.md section 8)
OBSERVABLE = 0.5
LOW_RATE = float(np.radians(0.5))  # rad/s: blocks slower than this give the |g| figures
VALLEY_SAMPLES = 32  # antithetic pairs of mounting errors for the valley's even part


def mounting_valley(pb: es.Problem, theta: np.ndarray, P: np.ndarray) -> np.ndarray | None:
    """(9, 9) over gyro_K's entries (row-major): the covariance the mountings' uncertainty
    adds to the gyro scale factors at second order, which the linearised covariance cannot
    see. The gyros measure K a_c(u_c) for each cycle c; a mounting error d moves a_c along
    a circle, so K changes by dK(d) with dK a_c(u + d) = K a_c(u) - K a_c(u + d). Its odd
    part in d is the linear trade already in the covariance; its even part (the axis's
    component along itself falls by |d|^2 / 2) is not, and on a vertical table axis, where
    nothing but the plan's attitude fixes the mountings, it is the diagonal's largest
    term: (mounting sigma)^2, 2.7e-5 at 0.3 deg. E[q q^T] of the even part q, d drawn from
    the mountings' covariance (a fixed Sobol sequence, so a record gives one answer).
    None where the model has no gyro_K or no cycle rotates."""
    pm = pb.pm
    if "gyro_K" not in pm.model.neutral_params():
        return None
    rot = [(c, cy) for c, cy in enumerate(pb.cycles) if not cy.static]
    if not rot:
        return None
    idx = np.concatenate([pm.idx["mount"][c] for c, _ in rot])
    w, V = np.linalg.eigh(0.5 * (P[np.ix_(idx, idx)] + P[np.ix_(idx, idx)].T))
    L = V * np.sqrt(np.clip(w, 0.0, None))
    K = np.asarray(pm.params(theta)["gyro_K"], float)
    u0 = [theta[pm.idx["mount"][c]] for c, _ in rot]
    a0 = np.array([axis_in_body(cy, u)[0] for (_, cy), u in zip(rot, u0)])
    from scipy.stats import norm, qmc  # here: SciPy's stats take ~1 s to import

    z = norm.ppf(qmc.Sobol(len(idx), scramble=True, seed=0).random(VALLEY_SAMPLES))
    Q = np.zeros((9, 9))
    for zi in z:
        d = (L @ zi).reshape(len(rot), 2)
        dK = []
        for sign in (1.0, -1.0):
            A = np.array([axis_in_body(cy, u + sign * dc)[0]
                          for (_, cy), u, dc in zip(rot, u0, d)])
            dK.append(np.linalg.lstsq(A, (a0 - A) @ K.T, rcond=None)[0].T)
        q = 0.5 * (dK[0] + dK[1]).ravel()
        Q += np.outer(q, q)
    return Q / len(z)


def theta_labels(pb: es.Problem) -> list:
    """A name per parameter-vector entry (messages, carrying a state across problems)."""
    pm = pb.pm
    out = [""] * pm.size
    for q, (key, flat) in enumerate(pm.keys):
        shape = pm.model.spec(key).shape
        ij = np.unravel_index(flat, shape) if shape else ()
        out[pm.idx["packing"][q]] = f"{key}[{','.join(str(int(v)) for v in ij)}]"
    names = {"lever_arm": "lever_arm", "mount": "mounting", "tilt": "table_tilt",
             "runout": "runout", "enc_zero": "angle_zero", "enc_opr": "angle_once_per_rev",
             "enc_scale": "angle_scale", "rate_scale": "rate_scale", "rate_bias": "rate_offset",
             "rate_zero": "rate_zero", "time_offset": "time_offset"}
    for g, name in names.items():
        if not pm.has(g):
            continue
        idx = pm.idx[g]
        for pos in np.ndindex(idx.shape):
            out[idx[pos]] = f"{name}[{','.join(str(v) for v in pos)}]"
    return out


def _reported(pb: es.Problem, theta: np.ndarray):
    """(packing of the reported keys, T: each reported entry as a row over theta (the
    linearisation at theta), the prior sd of each reported entry)."""
    pm, model = pb.pm, pb.pm.model
    keys = [k for k in (*IMU_KEYS, "proof_mass_offsets") if k in {s.key for s in model.specs()}]
    extra = [s.key for s in model.specs() if s.key not in keys and s.key != "lever_arm"]
    keys += extra
    if pm.has("lever_arm"):
        keys.insert(5, "lever_arm")
    specs, masks = [], []
    for k in keys:
        spec = model.spec(k)
        specs.append(spec)
        if k == "lever_arm":
            masks.append(np.array([np.abs(cy.basis).sum(axis=1) > 0 for cy in pm.rotating()]))
        else:
            masks.append(~spec.fixed_mask())
    packing = Packing(tuple(specs), tuple(masks))
    T = np.zeros((packing.size, pm.size))
    for q, (key, flat) in enumerate(packing.labels()):
        if key == "lever_arm":  # s = gamma^2 basis u: its linearisation at theta
            c, e = divmod(flat, 3)
            ds_du, ds_dG, gi = pm.lever_jacobian(theta, c)
            T[q, pm.idx["lever_arm"][c]] = ds_du[e]  # (c: the rotating cycle's row)
            T[q, gi] += ds_dG[e]
        elif key == "time_offset":
            T[q, pm.idx["time_offset"][0]] = 1.0
        else:
            T[q, pm.model_index(key, flat)] = 1.0
    prior = np.sqrt(np.diag(T @ np.diag(pm.sd**2) @ T.T))
    return packing, T, prior


def data_sigma(S: np.ndarray, pm, T: np.ndarray, prior_sd: np.ndarray) -> np.ndarray:
    """Each reported entry's sigma from the data and the informative priors alone, in units
    of its prior sigma (inf where nothing determines it)."""
    sd = pm.sd
    drop = np.where(pm.informative, 0.0, 1.0 / sd**2)
    Sd = (S - np.diag(drop)) * np.outer(sd, sd)  # dimensionless: the prior is the identity
    Sd = 0.5 * (Sd + Sd.T) + 1e-12 * np.eye(len(sd))
    try:
        cov = np.linalg.inv(Sd)
    except np.linalg.LinAlgError:
        cov = np.linalg.pinv(Sd)
    Ts = T * sd[None, :]
    var = np.einsum("ij,jk,ik->i", Ts, cov, Ts)
    return np.sqrt(np.clip(var, 0, None)) / prior_sd


def structural_unobservable(pb) -> set:
    """What a record without a gravity reference (every table axis vertical, no mounting
    stated, no static position of known attitude) cannot determine whatever the
    linearisation says: a common tilt of the mountings turns the accelerometers' K and
    biases, the lever arms and proof-mass offsets and the gyros' misalignment together
    at nearly equal cost (measured: 16 sigma apart for 11 in chi^2, along a curved path
    the local covariance does not see). Entries {key} or {(key, flat)}; the gyro scale
    about each axis stays where a cycle about it has an angle channel. With a stated
    mounting as the only gravity reference, the gyro scale about a body axis whose every
    cycle turns about a vertical table axis without an angle channel (fit.hold_undetermined
    pins it); nothing where a static position is in the record."""
    if any(cy.static for cy in pb.cycles):  # the turns between static positions of
        return set()  # known attitude measure the gyro scale (pinned, chi^2/dof 140-17874)
    out = set()
    for i in range(3):  # the gyro scale about body axis i on vertical axes: only an angle
        # channel about it fixes it (else the earth rate's phase and omega^2 against
        # d omega / dt, too weak and curved to converge on: 8 passes still moving 6 sigma)
        about = [(c, cy) for c, cy in enumerate(pb.cycles)
                 if not cy.static and abs(cy.a_nom[i]) > np.cos(VERTICAL)]
        if about and not any(pb.enc is not None and pb.enc[c] is not None
                             or not vertical(cy) for c, cy in about):
            out.add(("gyro_K", 4 * i))
    if gravity_reference(pb.cycles):
        return out
    out |= {"accel_bias", "accel_K", "lever_arm", "proof_mass_offsets"}
    for k in range(9):
        i, j = divmod(k, 3)
        if i != j:
            out.add(("gyro_K", k))
    for i in range(3):  # no cycle about the axis: nothing else fixes its scale either
        if not any(pb.enc is not None and pb.enc[c] is not None
                   and abs(cy.a_nom[i]) > np.cos(VERTICAL)
                   for c, cy in enumerate(pb.cycles) if not cy.static):
            out.add(("gyro_K", 4 * i))
    return out


def gravity_reference_words(pb) -> str:
    """Where the accelerometers' gravity reference comes from (stats.gravity_reference)."""
    if gravity_reference(pb.cycles):
        return "the rotating cycles (a table axis away from the vertical, or a stated mounting)"
    if any(cy.static for cy in pb.cycles):
        return "the static positions of known attitude (every table axis is vertical)"
    return ("none: every table axis is vertical and no mounting is stated (attitude_sigma_deg): "
            "the accelerometers, the lever arms and the gyros' misalignment are not determined")


def _g_errors(pb, pr, params) -> tuple:
    """|mean f| - g over the blocks slower than LOW_RATE, raw and corrected (m/s^2)."""
    K = np.asarray(params["accel_K"], float)
    b = np.asarray(params["accel_bias"], float)
    g = pb.rec.site.gravity
    raw, cor = [], []
    for cs, gp in zip(pr.systems, pr.gps):
        slow = gp.wabs < LOW_RATE
        if not slow.any():
            continue
        z = cs.accel.z[slow]
        raw += list(np.linalg.norm(z, axis=1) - g)
        cor += list(np.linalg.norm(np.linalg.solve(K, (z - b).T).T, axis=1) - g)
    if not raw:
        return None, None
    return float(np.sqrt(np.mean(np.square(raw)))), float(np.sqrt(np.mean(np.square(cor))))


def held_scales(pb: es.Problem) -> np.ndarray:
    """The theta indices of the gyro scale factors (K's diagonal) in pb.held: pinned at
    their prior mean where a gravity reference fixes the rest (fit.hold_undetermined),
    reported at it always."""
    return np.array([int(pb.pm.idx["packing"][q]) for q, kf in enumerate(pb.pm.keys)
                     if kf in pb.held and kf[0] == "gyro_K" and kf[1] % 4 == 0], int)


def _clipped(rec, cycles) -> list[int]:
    """Per accelerometer axis, samples of the cycles that sit exactly at the axis's extreme
    value: a saturated sensor repeats its full-scale reading, noise never does."""
    A = np.concatenate([rec.accel[cy.sl] for cy in cycles])
    out = []
    for i in range(A.shape[1]):
        col = A[:, i]
        n = int(np.sum(col == col.max())) + int(np.sum(col == col.min()))
        out.append(n if n > 10 else 0)
    return out


def considered(S: np.ndarray, pinned: np.ndarray, var: np.ndarray) -> np.ndarray:
    """The covariance of an estimate that held ``pinned`` at their prior means (variance
    ``var``) and fitted the rest given them (S: the information with the priors): the
    rest's conditional covariance plus the pinned entries' prior spread carried through
    their sensitivity (a consider covariance; the data's weak hold on the pinned entries
    is not counted: they never moved)."""
    free = np.setdiff1d(np.arange(len(S)), pinned)
    Pf = np.linalg.inv(S[np.ix_(free, free)])
    G = -Pf @ S[np.ix_(free, pinned)]
    out = np.zeros_like(S)
    out[np.ix_(free, free)] = Pf + (G * var) @ G.T
    out[np.ix_(free, pinned)] = G * var
    out[np.ix_(pinned, free)] = (G * var).T
    out[np.ix_(pinned, pinned)] = np.diag(var)
    return out


def build(pb: es.Problem, st: es.State, pr: es.PassResult, info: dict, light: bool = False):
    """The CalibrationResult of a converged fit; ``light``: without the sigma history, the
    mountings' valley and the position check (a diagnosis's scored candidates, never shown)."""
    pm, model, opt = pb.pm, pb.pm.model, pb.opt
    theta, cov_full = st.theta, pr.step.cov
    packing, T, prior_sd = _reported(pb, theta)
    if len(pb.pinned):
        cov_full = considered(pr.step.S, pb.pinned, pm.sd[pb.pinned] ** 2)
    cov = T @ cov_full @ T.T
    # (a scored candidate's gyro_K sigma is never read: diagnose.py's _new_entries)
    valley = None if light else mounting_valley(pb, theta, cov_full)
    if valley is not None:
        rows = [q for q, (k, _) in enumerate(packing.labels()) if k == "gyro_K"]
        flats = [f for k, f in packing.labels() if k == "gyro_K"]
        cov[np.ix_(rows, rows)] += valley[np.ix_(flats, flats)]
    dsig = data_sigma(pr.step.S, pm, T, prior_sd)
    unobs = ~(dsig < OBSERVABLE)
    labels = packing.labels()
    held = pb.held
    unobs |= np.array([(k, f) in held or k in held for k, f in labels], bool)
    imu = np.array([k in IMU_KEYS for k, _ in labels])
    if imu.any() and unobs[imu].all():
        raise EstimationError("the record determines none of the unit's parameters (every "
                              "bias, scale and misalignment entry is held by the priors "
                              "alone): record cycles with the table axis along different "
                              "body axes, at several rates")
    cov[unobs, :] = np.nan
    cov[:, unobs] = np.nan
    # a gyro scale nothing determines is reported at its nominal value: free along its
    # valley it ended at 1.45-1.80 on a vertical axis without channels, which `calib apply`
    # would have used (the reported entries do not depend on it: it is held)
    theta, scales = theta.copy(), held_scales(pb)
    theta[scales] = pm.mean[scales]
    params = pm.params(theta, pb.lever_known)
    # the values through the parameter map (the lever arm is not linear in theta); T is
    # its linearisation there, for the covariance
    vals = packing.pack({**params, **({"time_offset": theta[pm.idx["time_offset"]]}
                                      if pm.has("time_offset") else {})})
    fit = LsqFit(theta=vals, cov=cov, unobservable=unobs, residuals=np.zeros(0),
                 chi2=float("nan"), dof=0, nfev=0)
    base = dict(params)
    nc = len(pm.rotating())
    extra, pm_fixed = {}, []
    if opt.lever_arm == "known":
        extra["lever_arm"] = pb.lever_known
    elif opt.lever_arm == "off":
        extra["lever_arm"] = np.zeros((nc, 3))
    if not model.has("g_sensitivity"):  # reported, not estimated (the diagnosis's base)
        extra["gyro_D"] = np.zeros((3, 3))
    if not model.has("proof_mass_offsets"):  # always reported (CONTRACT.md section 7)
        extra["proof_mass_offsets"] = np.zeros((3, 3))
        pm_fixed = [f"proof_mass_offsets[{i},{j}]" for i in range(3) for j in range(3) if i != j]
    stats = _stats(pb, st, pr, info, params)
    tables = {} if light else history_tables(pb, st, pr)
    res = build_result("turntable", model, packing, fit, base, pb.rec.units, stats,
                       serial=pb.rec.serial, tables=tables, extra_unobservable=pm_fixed)
    for k, v in extra.items():  # reported, not estimated
        res.params[k] = np.asarray(v, float)
        res.sigma[k] = (np.zeros((nc, 3)) if k == "lever_arm" else np.zeros((3, 3))
                        if k == "gyro_D" else np.where(np.eye(3) > 0, 0.0, np.nan))
        res.units[k] = "m"
    order = [k for k in (*IMU_KEYS, "lever_arm", "proof_mass_offsets") if k in res.params]
    for d in (res.params, res.sigma, res.units):
        items = {k: d.pop(k) for k in order}
        rest = {k: d.pop(k) for k in list(d)}
        d.update(items)
        d.update(rest)
    if not light:
        from calib_cli.methods.check_positions import check_positions

        res.stats["check_positions"] = check_positions(pb.rec, res)
    return res


def _stats(pb, st, pr, info, params) -> dict:
    pm, opt = pb.pm, pb.opt
    P = pr.step.cov
    sig_a = pb.sig_a * st.inflation
    rms = info.get("residual_rms", {})
    res_acc = []
    from calib_cli.methods.turntable.solve import residuals_after

    for cs, dl in zip(pr.systems, pr.step.dlocal):
        r = residuals_after(cs, dl, pr.step.dtheta)[:, ACC]
        res_acc.append(r[cs.weight[:, 0] > 0])
    res_acc = np.concatenate(res_acc) if res_acc else np.zeros((0, 3))
    before, after = _g_errors(pb, pr, params)
    a_b, u_sd = [], []
    for c, cy in enumerate(pb.cycles):  # (the mounting's rows: every cycle's, static too)
        if cy.static:
            continue
        u = st.theta[pm.idx["mount"][c]]
        v = cy.a_nom + cy.basis @ u
        a_b.append([float(x) for x in v / np.linalg.norm(v)])
        u_sd.append([float(np.sqrt(P[i, i])) for i in pm.idx["mount"][c]])
    tilts = []
    for gidx in range(pm.idx["tilt"].shape[0]):
        cy = next(c for c in pm.rotating() if c.axis_group == gidx)
        ii = pm.idx["tilt"][gidx]
        sd = [float(np.sqrt(P[i, i])) for i in ii]
        tilts.append({"plan_axis_enu": [float(v) for v in cy.a_enu],
                      "perpendicular_enu": [[float(v) for v in r] for r in perp_basis(cy.a_enu).T],
                      "tilt_mrad": [float(st.theta[i]) * 1e3 for i in ii],
                      "sigma_mrad": [None if v > 0.5 * opt.table_tilt_sigma else v * 1e3
                                     for v in sd]})
    runout = []
    if pm.has("runout"):
        for c in range(len(pm.rotating())):
            x = st.theta[pm.idx["runout"][c]]
            runout.append([float(np.hypot(x[0], x[1])) * 1e6, float(np.hypot(x[2], x[3])) * 1e6])
    block_s = pb.block_n / pb.rec.sample_rate
    return {
        "accel_residual_rms": float(np.sqrt(np.mean(res_acc**2))) if len(res_acc) else None,
        "normalized_innovation_rms": rms.get("accel"),
        "g_error_rms_before": before, "g_error_rms_after": after,
        "n_cycles": len(pm.rotating()), "cycles": [cy.label for cy in pm.rotating()],
        "static_positions_used": [cy.label for cy in pb.cycles if cy.static],
        "gravity_reference": gravity_reference_words(pb),
        "lever_arm_mode": opt.lever_arm, "proof_mass_mode": opt.proof_mass,
        "tangential": bool(opt.tangential), "block_s": block_s, "passes": int(opt.passes),
        "grade": opt.grade, "prior_sigma": {k: float(v) for k, v in prior_widths(opt).items()},
        "accel_noise_inflation": float(st.inflation),
        "noise_accel": [float(v) for v in sig_a], "noise_gyro": [float(v) for v in pb.sig_g],
        "table_axis_body": a_b, "table_axis_body_sigma_rad": u_sd,
        "mounting_sigma_deg": [float(np.degrees(cy.mount_sigma)) for cy in pm.rotating()],
        "mounting_stated": [bool(cy.mount_stated) for cy in pm.rotating()],
        "table_axis_tilt_mrad": tilts,
        "g_error_floor": float(np.sqrt(np.mean(sig_a**2) / pb.block_n)),
        "g_error_note": f"|mean f| - g over blocks of {block_s:g} s where the table is at rest",
        "accel_clipped_samples": _clipped(pb.rec, pm.rotating()),
        "table_axis_noise_mrad": float(np.sqrt(st.axis_var) * 1e3),
        "table_axis_noise_mode": "given" if opt.axis_sigma is not None else "estimated",
        "table_axis_runout_urad": runout,
        "filter_passes": int(info["passes"]), "start_windows": int(info["start_windows"]),
        "filter_last_move_sigma": info.get("last_move"),
        "residual_rms_normalised": {k: float(v) for k, v in rms.items()},
        "table_encoder": _channel_stats(pb, st, P, rms),
    }


def _channel_stats(pb, st, P, rms) -> dict:
    """What the table's channels contributed (stats.table_encoder)."""
    pm = pb.pm
    out = {}
    if pb.rate is not None:
        ik, ib = pm.idx["rate_scale"][0], pm.idx["rate_bias"][0]
        out.update({
            "rate_cycles_used": [r is not None for r in pb.rate],
            "rate_scale_error": float(st.theta[ik]),
            "rate_scale_error_sigma": float(np.sqrt(P[ik, ik])),
            "rate_offset_dps": float(np.degrees(st.theta[ib])),
            "rate_offset_sigma_dps": float(np.degrees(np.sqrt(P[ib, ib]))),
            "rate_reading_sigma_dps": float(np.degrees(pb.sig_rate)),
            "rate_normalized_innovation_rms": rms.get("rate")})
    if pb.enc is None:
        return {"mode": "rate" if pb.rate is not None else "off", **out, "notes": pb.notes}
    io = pm.idx["enc_opr"]
    isc = pm.idx["enc_scale"][0]
    return {"mode": "both" if pb.rate is not None else "angle", **out,
            "cycles_used": [e is not None for e in pb.enc],
            "sign": [None if e is None else e.sign for e in pb.enc],
            "once_per_rev_mrad": [float(st.theta[i]) * 1e3 for i in io],
            "once_per_rev_sigma_mrad": [float(np.sqrt(P[i, i])) * 1e3 for i in io],
            "scale_error": float(st.theta[isc]),
            "reading_sigma_urad": pb.sig_enc * 1e6,
            "white_noise_urad": pb.sig_enc_floor * 1e6,
            "normalized_innovation_rms": rms.get("angle"), "notes": pb.notes}


def history_tables(pb, st, pr) -> dict:
    """The sigma history of the lever arms and proof-mass offsets (filled by history.py)."""
    from calib_cli.methods.turntable.history import sigma_history

    return sigma_history(pb, pr)


def grade_widths(grade: str) -> dict:
    return dict(GRADES[grade])
