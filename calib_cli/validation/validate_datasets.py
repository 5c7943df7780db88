"""Comparisons with established tools on their own real recordings
(docs/validation/datasets.md). ``python -m calib_cli.validation.validate_datasets DATASETS OUT.md``
writes the tables; the tests in tests/test_datasets.py check the numbers.

Datasets (shared/datasets, see each folder's README):
- imu_tk_xsens_mti: Xsens MTi, raw counts, ~38 hand-placed static attitudes
  (imu_tk's test data), compared with the manufacturer's parameters and
  imu_tk's published output.
- imucal_ferraris: the six-positions-plus-three-turns protocol of imucal;
  annotated_session.csv against imucal's regression result, and the
  unsegmented example session (no published result).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from calib_cli.io.plan import parse_plan
from calib_cli.io.textlog import import_text
from calib_cli.methods.accel_lsq import fit_accel
from calib_cli.methods.gyro import fit_gyro
from calib_cli.methods.segstats import static_stats

R2D = 180.0 / np.pi

# -- published reference numbers (dataset READMEs) ----------------------------
XSENS_G = 9.81744
XSENS_ACC_SCALE = np.array([415.0, 413.0, 415.0])  # counts/(m/s^2), manufacturer
XSENS_ACC_MIS = np.array([[1, 0, -0.01], [0.01, 1, 0.01], [0.02, 0.01, 1]])
XSENS_GYRO_SCALE = np.array([4778.0, 4758.0, 4766.0])  # counts/(rad/s), manufacturer
XSENS_GYRO_MIS = np.array([[1, -0.01, -0.02], [0, 1, 0.04], [-0.01, 0.01, 1]])
IMUTK_ACC_T = np.array([[1, -0.0033593, -0.00890639], [0, 1, -0.0213341], [0, 0, 1]])
IMUTK_ACC_K = np.diag([0.00241278, 0.00242712, 0.00241168])  # (m/s^2)/count
IMUTK_ACC_B = np.array([33124.2, 33275.2, 32364.4])
IMUTK_ACC_INV_SCALE = np.array([414.459, 412.01, 414.649])
IMUTK_GYRO_T = np.array([[1, 0.00593634, 0.00111101], [0.00808812, 1, -0.0535569],
                         [0.0253067, -0.0025513, 1]])
IMUTK_GYRO_INV_SCALE = np.array([4777.96, 4764.21, 4773.66])
IMUTK_GYRO_B = np.array([32777.1, 32459.8, 32511.8])
IMUTK_G_RMS_README = 1.13e-3  # m/s^2, on the README's 38 windows

XSENS_PLAN = """name = "imu_tk xsens mti"
kind = "static"
[site]
g = 9.81744
[[segment]]
label = "pos"
repeat = "auto"
"""

_FERRARIS_STATIC = [("x_p", [0, -90, 0]), ("x_a", [0, 90, 0]), ("y_p", [90, 0, 0]),
                    ("y_a", [-90, 0, 0]), ("z_p", [0, 0, 0]), ("z_a", [180, 0, 0])]


def ferraris_plan(angle_deg: float) -> str:
    """The six positions (+x, -x, +y, -y, +z, -z up) and three turns of
    ``angle_deg`` about x, y, z (each about the vertical), imucal's labels."""
    out = ['name = "ferraris"', 'kind = "static"', 'protocol = "ferraris"', "[site]", "g = 9.81"]
    for label, att in _FERRARIS_STATIC:
        out += ["[[segment]]", f'label = "{label}"', f"attitude_deg = {att}"]
    for label, ax in (("x_rot", [1, 0, 0]), ("y_rot", [0, 1, 0]), ("z_rot", [0, 0, 1])):
        out += ["[[segment]]", f'label = "{label}"', f"rotation_axis_body = {ax}",
                f"rotation_angle_deg = {angle_deg}"]
    return "\n".join(out) + "\n"


def lower_times_rotation(K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """K = L Q with L lower triangular (positive diagonal) and Q a rotation
    (from the QR factorisation of K^T)."""
    q, r = np.linalg.qr(K.T)
    d = np.diag(np.sign(np.diag(r)))
    L, Q = (d @ r).T, (q @ d).T
    if np.linalg.det(Q) < 0:  # not reachable for det K > 0; keep Q proper anyway
        raise ValueError("K has a negative determinant")
    return L, Q


def row_normalised(M: np.ndarray) -> np.ndarray:
    """Each row divided by its diagonal entry: the misalignment part of S M."""
    return M / np.diag(M)[:, None]


def _rms(x) -> float:
    return float(np.sqrt(np.mean(np.square(x))))


# ---------------------------------------------------------------------------
# Xsens MTi (imu_tk)


def xsens(root: Path) -> dict:
    d = Path(root) / "imu_tk_xsens_mti"
    plan = parse_plan(XSENS_PLAN, "xsens.toml")
    rec = import_text(d / "xsens_acc.mat", plan, d / "xsens_gyro.mat", accel_units="count",
                      gyro_units="count")
    acc = fit_accel(rec, "scalar")
    gyr = fit_gyro(rec, acc)
    st = static_stats(rec, "accel")
    windows = [(float(rec.time[s.start]), float(rec.time[s.stop - 1])) for s in st.segments]
    # the toolkit's published accelerometer parameters on the same windows
    f_tk = (st.means - IMUTK_ACC_B) @ (IMUTK_ACC_T @ IMUTK_ACC_K).T
    g_tk = np.linalg.norm(f_tk, axis=1)
    Ka = np.asarray(acc.params["accel_K"])
    f = np.linalg.solve(Ka, (st.means - acc.params["accel_bias"]).T).T
    g_ours = np.linalg.norm(f, axis=1)
    # the manufacturer's matrices in the frame the accelerometers fix
    L, Q = lower_times_rotation(np.diag(XSENS_ACC_SCALE) @ XSENS_ACC_MIS)
    G_man = np.diag(XSENS_GYRO_SCALE) @ XSENS_GYRO_MIS @ Q.T
    G = np.asarray(gyr.params["gyro_K"])
    n_acc_params = int(sum(1 for k, _ in acc.cov_order))
    return {
        "n_samples": len(rec), "windows": windows, "window_samples": st.counts.tolist(),
        "g_rms_ours": _rms(g_ours - XSENS_G), "g_rms_imutk": _rms(g_tk - XSENS_G),
        "g_mean_ours": float(g_ours.mean()), "g_mean_imutk": float(g_tk.mean()),
        "n_params_ours": n_acc_params, "n_params_imutk": 9,
        "acc_scale": np.diag(Ka), "acc_scale_rel": np.diag(Ka) / XSENS_ACC_SCALE - 1,
        "acc_bias": np.asarray(acc.params["accel_bias"]),
        "gyro_scale": np.diag(G), "gyro_scale_rel": np.diag(G) / XSENS_GYRO_SCALE - 1,
        "gyro_bias": np.asarray(gyr.params["gyro_bias"]),
        "acc_mis_ours": row_normalised(Ka), "acc_mis_man": row_normalised(L),
        "gyro_mis_ours": row_normalised(G), "gyro_mis_man": row_normalised(G_man),
        "acc_mis_maxdiff": float(np.abs(row_normalised(Ka) - row_normalised(L)).max()),
        "gyro_mis_maxdiff": float(np.abs(row_normalised(G) - row_normalised(G_man)).max()),
        "Q": Q, "gyro_D": np.asarray(gyr.params.get("gyro_D", np.zeros((3, 3)))),
        "gyro_stats": gyr.stats, "accel_stats": acc.stats,
        "gyro_sigma_K": np.asarray(gyr.sigma["gyro_K"]),
    }


# ---------------------------------------------------------------------------
# imucal Ferraris


def _imucal_turn_angles(rec, ref: dict) -> dict:
    """imucal's own parameters applied to the turn segments, integrated (deg)."""
    Ka, Ra, ba = (np.asarray(ref[k]) for k in ("K_a", "R_a", "b_a"))
    Kg, Rg, Kga, bg = (np.asarray(ref[k]) for k in ("K_g", "R_g", "K_ga", "b_g"))
    out = {}
    for s in rec.segments:
        if s.kind != "turn":
            continue
        acc = np.linalg.solve(Ka @ Ra, (rec.accel[s.slice] - ba).T).T
        w = np.linalg.solve(Kg @ Rg, (rec.gyro[s.slice] - acc @ Kga.T - bg).T).T  # deg/s
        out[s.label] = float(w.sum(axis=0) @ s.rotation_axis_body / rec.sample_rate)
    return out


def _raw_turn_angles(rec, res) -> dict:
    """Integral over each turn of (W - d) / G_ii about the turn's axis (deg): the
    angle the raw gyro measures with positive scale factors."""
    d, G = np.asarray(res.params["gyro_bias"]), np.asarray(res.params["gyro_K"])
    out = {}
    for s in rec.segments:
        if s.kind == "turn":
            i = int(np.argmax(np.abs(s.rotation_axis_body)))
            x = rec.gyro[s.slice, i] - d[i]
            area = float(np.sum(0.5 * (x[1:] + x[:-1]) * np.diff(rec.time[s.slice])))
            out[s.label] = area / abs(G[i, i]) * R2D  # trapezoid (numpy 1.26 has no trapezoid)
    return out


def ferraris_annotated(root: Path) -> dict:
    d = Path(root) / "imucal_ferraris"
    ref = json.loads((d / "expected_example_cal_annotated_session.json").read_text())
    plan = parse_plan(ferraris_plan(360.0), "ferraris.toml")
    rec = import_text(d / "annotated_session.csv", plan,
                      columns="time=samples,ax=acc_x,ay=acc_y,az=acc_z,gx=gyr_x,gy=gyr_y,"
                              "gz=gyr_z,segment=part",
                      accel_units="count", gyro_units="count", rate=204.8, time_unit="sample",
                      sort=True)
    res = fit_gyro(rec)
    Ka = np.asarray(res.params["accel_K"])
    G = np.asarray(res.params["gyro_K"])
    K_ref = np.asarray(ref["K_a"]) @ np.asarray(ref["R_a"])
    # imucal: raw = K_g R_g w(deg/s) with R_g ~ -I from its -360 deg convention
    G_ref = -np.asarray(ref["K_g"]) @ np.asarray(ref["R_g"]) * R2D
    return {
        "acc_scale": np.diag(Ka), "acc_scale_ref": np.diag(np.asarray(ref["K_a"])),
        "acc_scale_rel": np.diag(Ka) / np.diag(np.asarray(ref["K_a"])) - 1,
        "gyro_scale_dps": np.diag(G) / R2D, "gyro_scale_ref_dps": np.diag(np.asarray(ref["K_g"])),
        "gyro_scale_rel": (np.diag(G) / R2D) / np.diag(np.asarray(ref["K_g"])) - 1,
        "accel_K": Ka, "accel_K_ref": K_ref, "accel_bias": np.asarray(res.params["accel_bias"]),
        "accel_bias_ref": np.asarray(ref["b_a"]),
        "gyro_K": G, "gyro_K_ref": G_ref, "gyro_bias": np.asarray(res.params["gyro_bias"]),
        "gyro_bias_ref": np.asarray(ref["b_g"]),
        "gyro_D": np.asarray(res.params["gyro_D"]), "gyro_D_ref": np.asarray(ref["K_ga"]),
        "raw_turn_deg": _raw_turn_angles(rec, res),
        "imucal_turn_deg": _imucal_turn_angles(rec, ref),
        "stats": res.stats, "accel_method": res.stats.get("accel_method"),
    }


def ferraris_example(root: Path) -> dict:
    d = Path(root) / "imucal_ferraris"
    out = {}
    for angle in (-360.0, 360.0):
        plan = parse_plan(ferraris_plan(angle), "ferraris.toml")
        rec = import_text(d / "example_ferraris_session.csv", plan, gyro_units="deg/s",
                          rate=102.4, time_unit="sample",
                          segments_json=str(d / "example_ferraris_session_list.json"))
        res = fit_gyro(rec)
        out[angle] = {"accel_K": np.asarray(res.params["accel_K"]),
                      "accel_bias": np.asarray(res.params["accel_bias"]),
                      "gyro_K": np.asarray(res.params["gyro_K"]),
                      "gyro_bias": np.asarray(res.params["gyro_bias"]),
                      "gyro_D": np.asarray(res.params["gyro_D"]) if "gyro_D" in res.params
                      else None,
                      "sigma_gyro_K": np.asarray(res.sigma["gyro_K"]), "stats": res.stats,
                      "raw_turn_deg": _raw_turn_angles(rec, res)}
    return out


# ---------------------------------------------------------------------------
# markdown


def _m(M, fmt="{:.4f}") -> str:
    M = np.atleast_2d(M)
    return "<br>".join("[" + ", ".join(fmt.format(x) for x in row) + "]" for row in M)


def _v(v, fmt="{:.4g}") -> str:
    return ", ".join(fmt.format(x) for x in np.ravel(v))


def markdown(root: Path) -> str:
    x = xsens(root)
    fa = ferraris_annotated(root)
    fe = ferraris_example(root)
    L = []
    L += ["# Validation on real recordings", "",
          "Generated by `make validate` (tests/test_datasets.py::test_write_validation_md, "
          "or `python -m calib_cli.validation.validate_datasets shared/datasets "
          "docs/validation/datasets.md`). "
          "Do not edit by hand.", ""]
    L += ["## 1. Xsens MTi, imu_tk test data (raw counts, hand-placed)", "",
          "Import: `calib import text xsens_acc.mat xsens_gyro.mat --plan xsens.toml "
          "--accel-units count --gyro-units count` with one `repeat = \"auto\"` segment and "
          "`g = 9.81744` (as imu_tk's run). Static detection with the defaults (1 s window, "
          f"3x the noise floor, >= 1 s) finds **{len(x['windows'])} windows**, listed at the "
          "end of this section.", "",
          "### Accelerometer (scalar method, lower-triangular K: 3 bias + 6 K = "
          f"{x['n_params_ours']} parameters; imu_tk: 3 bias + 3 scale + 3 misalignment = 9)", "",
          "| quantity | calib | imu_tk (published parameters) | manufacturer |",
          "|---|---|---|---|",
          f"| RMS of mean |f| - g over the {len(x['windows'])} windows, m/s^2 | "
          f"**{x['g_rms_ours']:.4g}** | {x['g_rms_imutk']:.4g} on the same windows "
          f"({IMUTK_G_RMS_README:.3g} on the README's windows) | - |",
          f"| mean |f| over the windows, m/s^2 | {x['g_mean_ours']:.6f} | "
          f"{x['g_mean_imutk']:.6f} | - |",
          f"| scale factors, counts/(m/s^2) | {_v(x['acc_scale'], '{:.3f}')} | "
          f"{_v(IMUTK_ACC_INV_SCALE, '{:.3f}')} | {_v(XSENS_ACC_SCALE, '{:.0f}')} |",
          f"| scale vs manufacturer | {_v(100 * x['acc_scale_rel'], '{:+.3f}')} % | "
          f"{_v(100 * (IMUTK_ACC_INV_SCALE / XSENS_ACC_SCALE - 1), '{:+.3f}')} % | - |",
          f"| bias, counts | {_v(x['acc_bias'], '{:.1f}')} | {_v(IMUTK_ACC_B, '{:.1f}')} | "
          "33123, 33276, 32360 |",
          f"| misalignment (rows of K / diagonal) | {_m(x['acc_mis_ours'])} | T (upper, its "
          f"own frame): {_m(IMUTK_ACC_T)} | lower factor: {_m(x['acc_mis_man'])} |", "",
          f"Largest misalignment difference to the manufacturer: **{x['acc_mis_maxdiff']:.4f}** "
          "(the manufacturer gives its matrices to 0.01).", "",
          f"### Gyro (`calib fit gyro`: {x['gyro_stats']['n_transitions']} transitions between "
          "the static positions, full G, bias and g-sensitivity D)", "",
          "| quantity | calib | imu_tk (published) | manufacturer |", "|---|---|---|---|",
          f"| scale factors, counts/(rad/s) | {_v(x['gyro_scale'], '{:.1f}')} | "
          f"{_v(IMUTK_GYRO_INV_SCALE, '{:.1f}')} | {_v(XSENS_GYRO_SCALE, '{:.0f}')} |",
          f"| scale vs manufacturer | {_v(100 * x['gyro_scale_rel'], '{:+.3f}')} % | "
          f"{_v(100 * (IMUTK_GYRO_INV_SCALE / XSENS_GYRO_SCALE - 1), '{:+.3f}')} % | - |",
          f"| 1-sigma of the scale factors | {_v(np.diag(x['gyro_sigma_K']), '{:.2f}')} | - | - |",
          f"| bias, counts | {_v(x['gyro_bias'], '{:.1f}')} | {_v(IMUTK_GYRO_B, '{:.1f}')} "
          "(initial static period) | 32768, 32466, 32485 |",
          f"| misalignment in the accelerometer frame (rows / diagonal) | {_m(x['gyro_mis_ours'])} "
          f"| T (its own frame): {_m(IMUTK_GYRO_T)} | {_m(x['gyro_mis_man'])} |",
          f"| g-sensitivity D, counts/(m/s^2) | {_m(x['gyro_D'], '{:.3f}')} | - | - |",
          f"| transition residual RMS (gravity direction), deg | "
          f"{x['gyro_stats']['transition_residual_rms_rad'] * R2D:.3f} | - | - |", "",
          f"Largest misalignment difference to the manufacturer: **{x['gyro_mis_maxdiff']:.4f}**.",
          "",
          "### One frame for the comparison", "",
          "The manufacturer's matrices are in the housing frame: raw = S M x + b with S the "
          "diagonal scale and M the misalignment (rows as printed). calib's accelerometer K is "
          "lower triangular: its frame is the one the accelerometers fix (x along the x "
          "accelerometer, y in the plane of x and y). So the manufacturer's S_a M_a is "
          "factored as L Q (QR factorisation of its transpose; L lower triangular with a "
          "positive diagonal, Q a rotation from the housing frame into the accelerometer "
          "frame), and L is compared with calib's accel_K, each row divided by its diagonal. "
          "The gyro matrix is expressed in the same frame: W = S_g M_g w_housing = S_g M_g "
          "Q^T w_acc, so calib's gyro_K (fitted in the accelerometer frame, since the gravity "
          "directions come from the calibrated accelerometers) is compared with S_g M_g Q^T, "
          "rows divided by their diagonal. (S M and M S differ by < 1e-4 here.)", "",
          f"Q (housing -> accelerometer frame): {_m(x['Q'], '{:.5f}')}", "",
          "imu_tk's T matrices are in imu_tk's own frames (upper-triangular accelerometer T), "
          "so they are shown for reference only; its |g| residual is frame-free and is "
          "recomputed above from its published bias, K and T on calib's windows.", "",
          "Static windows used (start - end, s; samples):", "",
          ", ".join(f"{a:.2f}-{b:.2f} ({int(n)})" for (a, b), n in
                    zip(x["windows"], x["window_samples"], strict=False)), ""]
    # Ferraris annotated
    L += ["## 2. imucal Ferraris, annotated_session.csv (raw counts, 204.8 Hz)", "",
          "Import: `calib import text annotated_session.csv --plan ferraris.toml --columns "
          "time=samples,ax=acc_x,ay=acc_y,az=acc_z,gx=gyr_x,gy=gyr_y,gz=gyr_z,segment=part "
          "--time-unit sample --rate 204.8 --sort --accel-units count --gyro-units count` "
          "(the file lists the parts by label, `--sort` puts them in time order; the "
          "`part` column names plan segments). Plan: the six positions with their attitudes, "
          "`g = 9.81` (as imucal's run) and three turns `rotation_angle_deg = 360` about x, y, "
          "z. Fit: `calib fit gyro` (accelerometer by the vector method first).", "",
          "| quantity | calib | imucal (regression snapshot) | difference |", "|---|---|---|---|",
          f"| accel scale factors, counts/(m/s^2) | {_v(fa['acc_scale'], '{:.3f}')} | "
          f"{_v(fa['acc_scale_ref'], '{:.3f}')} | {_v(100 * fa['acc_scale_rel'], '{:+.3f}')} % |",
          f"| gyro scale factors, counts/(deg/s) | {_v(fa['gyro_scale_dps'], '{:.3f}')} | "
          f"{_v(fa['gyro_scale_ref_dps'], '{:.3f}')} | "
          f"{_v(100 * fa['gyro_scale_rel'], '{:+.3f}')} % |",
          f"| accel K vs K_a R_a, counts/(m/s^2) | {_m(fa['accel_K'], '{:.3f}')} | "
          f"{_m(fa['accel_K_ref'], '{:.3f}')} | |",
          f"| accel bias, counts | {_v(fa['accel_bias'], '{:.2f}')} | "
          f"{_v(fa['accel_bias_ref'], '{:.2f}')} | |",
          f"| gyro K vs -K_g R_g x 180/pi, counts/(rad/s) | {_m(fa['gyro_K'], '{:.2f}')} | "
          f"{_m(fa['gyro_K_ref'], '{:.2f}')} | |",
          f"| gyro bias, counts | {_v(fa['gyro_bias'], '{:.3f}')} | "
          f"{_v(fa['gyro_bias_ref'], '{:.3f}')} | |",
          f"| gyro D vs K_ga, counts/(m/s^2) | {_m(fa['gyro_D'], '{:.4f}')} | "
          f"{_m(fa['gyro_D_ref'], '{:.4f}')} | |",
          f"| turn angle from the raw gyro, (W - d)/G_ii integrated, deg | "
          f"{_v(list(fa['raw_turn_deg'].values()), '{:+.2f}')} | with imucal's parameters: "
          f"{_v(list(fa['imucal_turn_deg'].values()), '{:+.2f}')} | |", "",
          "Conventions, one by one:", "",
          "- **Units.** imucal's K_g is in counts per deg/s (its `gyr_unit` is deg/s); "
          "calib's gyro_K is in counts per rad/s. The table divides calib's by 180/pi. Both "
          "accelerometer matrices are in counts per m/s^2; imucal's b_g, K_ga and calib's "
          "gyro_bias, gyro_D are in counts and counts per m/s^2 alike.",
          "- **Matrix order.** imucal: raw = K_a R_a acc + b_a and raw = K_g R_g gyr + "
          "K_ga acc + b_g (K diagonal scale, R the misalignment, applied first). calib: "
          "A = b + K f and W = d + G w + D f, so calib's K corresponds to K_a R_a and G to "
          "K_g R_g (times the sign below); calib's diagonal scale factors are the diagonal "
          "of the product, which differs from imucal's K_a, K_g by the cosines of the "
          "misalignment angles (< 0.1 %).",
          "- **Frame.** Both define the body frame by the six positions (x, y, z up and down "
          "at known attitudes): calib's vector method with a full K, as imucal's R_a. The "
          "gyro matrices are in that same frame.",
          "- **Rotation sign.** imucal integrates each hand turn and expects -360 deg "
          "(its default `expected_angle`), which makes its R_g close to -I. Integrating this "
          "file's raw gyro over each turn, bias removed, with positive scale factors gives "
          f"{_v(list(fa['raw_turn_deg'].values()), '{:+.2f}')} deg: calib's plan states "
          "+360 deg (right-hand rule) and finds a G with a positive diagonal, -1 times "
          "imucal's K_g R_g. This file holds only the nine annotated parts spliced together "
          "(no motion between positions), so nothing in it tells the two signs apart; the "
          "corrected rates of the two calibrations differ in sign. In the unsegmented example "
          "session below, where the motions between positions are recorded, the gravity "
          "directions do decide the sign.",
          "- **Estimators.** imucal follows Ferraris's closed forms: the bias of each "
          "accelerometer axis from the two positions along that axis only ((U_p + U_a)/2, "
          "eq. 20), K_a and R_a from the differences of opposite positions, the gyro bias as "
          "the mean of all static samples, K_ga from the differences of opposite positions "
          "(eq. 9), and the turn integrals as sample sums / rate. calib fits bias and K by "
          "weighted least squares over all six positions (so each accelerometer bias also "
          "uses the four positions where that axis is horizontal: the x reading averaged over "
          "z up and z down is -12 counts, over x up and x down -6 counts; that "
          "inconsistency of the hand-held positions is the 1-8 count difference in the "
          "accelerometer bias), bias and D of the gyro jointly from the six static means, and "
          "integrates the turns with the trapezoidal rule.",
          "- **g-sensitivity.** Both fit a full 3x3 g-sensitivity from the six static "
          "positions (imucal K_ga, calib gyro_D); they agree within the noise of the static "
          "gyro means (~0.1 count per mean, i.e. up to ~0.01 count per m/s^2 in D).",
          "- **Earth rate.** imucal ignores it; calib includes it in the static gyro means "
          "using the plan's attitudes (yaw 0 assumed here, so it is approximate; 0.07 "
          "counts, below the noise of the means).", ""]
    # example session
    m, p = fe[-360.0], fe[360.0]
    L += ["## 3. imucal Ferraris, example_ferraris_session.csv (m/s^2, deg/s, 102.4 Hz)", "",
          "No published result. Import: `calib import text example_ferraris_session.csv "
          "--plan ferraris.toml --time-unit sample --rate 102.4 --gyro-units deg/s --segments "
          "example_ferraris_session_list.json` (imucal's region list: sample ranges by "
          "label). The session is continuous, so the gyro fit uses the 5 transitions "
          "between the static positions as well as the three turns.", "",
          "| quantity | plan turns -360 deg | plan turns +360 deg |", "|---|---|---|",
          f"| accel K | {_m(m['accel_K'])} | same |",
          f"| accel bias, m/s^2 | {_v(m['accel_bias'])} | same |",
          f"| gyro K | {_m(m['gyro_K'])} | {_m(p['gyro_K'])} |",
          f"| gyro bias, deg/s | {_v(m['gyro_bias'] * R2D)} | {_v(p['gyro_bias'] * R2D)} |",
          f"| transition residual RMS, deg | "
          f"{m['stats']['transition_residual_rms_rad'] * R2D:.3f} | "
          f"{p['stats']['transition_residual_rms_rad'] * R2D:.1f} |",
          f"| turn residual RMS, deg | {m['stats']['turn_residual_rms_rad'] * R2D:.3f} | "
          f"{p['stats']['turn_residual_rms_rad'] * R2D:.2f} |",
          "| raw turn angles (W - d)/G_ii, deg | "
          f"{_v(list(m['raw_turn_deg'].values()), '{:+.2f}')} "
          "| |", "",
          "With -360 deg (imucal's default) the transitions and the turns agree (G close to "
          "the identity, as expected of data already in deg/s); with +360 deg they contradict "
          "each other (G with a negative diagonal, transition residuals of tens of degrees). "
          "The turns in this session are clockwise about the up axis.", ""]
    return "\n".join(L)


def main(argv=None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    root = Path(argv[0]) if argv else Path(__file__).resolve().parents[2] / "shared" / "datasets"
    out = Path(argv[1]) if len(argv) > 1 else Path("docs/validation/datasets.md")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(markdown(root), encoding="utf-8")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
