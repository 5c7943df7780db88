"""PX4 and ArduPilot exports of fits on data the firmware had already
corrected (issue 34): composed with the parameters in force, checked through
each firmware's equation written out here from its source; instance names as
each firmware has them; PX4 TC_* thermal export; what cannot be exported
exits with the reason."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from calib_cli.data import CalibrationResult
from calib_cli.errors import EstimationError, InputError
from calib_cli.io import fc_params
from calib_cli.io.export_autopilot import UsageProblem, autopilot_export
from calib_cli.model.effects import temp_poly

B0 = np.array([0.05, -0.03, 0.08])  # sensor-frame truth: x = B0 + K0 f_s
K0 = np.array([[1.01, 0.002, -0.003], [0.001, 0.99, 0.004], [-0.002, 0.003, 1.005]])
D0 = np.array([0.002, -0.001, 0.003])
G0 = np.array([[1.002, 0.001, 0.0], [0.0, 0.998, -0.002], [0.001, 0.0, 1.001]])
# the example: offsets and scales in force
OFF = [0.12, -0.08, 0.20]
SCL = [1.003, 0.996, 1.002]
GOFF = [0.01, -0.02, 0.005]


def _cal(bias, K, gbias=None, G=None, **extra) -> CalibrationResult:
    p = {"accel_bias": np.asarray(bias, float), "accel_K": np.asarray(K, float)}
    if gbias is not None:
        p.update(gyro_bias=np.asarray(gbias, float), gyro_K=np.asarray(G, float))
    stats = extra.pop("stats", {})
    p.update(extra)
    from calib_cli.model.imu_model import base_model
    from calib_cli.model.truth import describe_effect

    model = [describe_effect(e) for e in base_model(gyro=gbias is not None).effects]
    return CalibrationResult(method="vector", params=p, sigma={}, units={},
                             covariance=np.zeros((0, 0)), cov_order=[], stats=stats,
                             model=model)


def _px4_params(rot=0, lvl=(0.0, 0.0, 0.0), slot=0, tc=None):
    p = {f"CAL_ACC{slot}_ID": 1234, f"CAL_GYRO{slot}_ID": 5678, "SENS_BOARD_ROT": rot,
         f"CAL_ACC{slot}_ROT": -1, f"CAL_GYRO{slot}_ROT": -1}
    for i, a in enumerate("XYZ"):
        p[f"CAL_ACC{slot}_{a}OFF"] = OFF[i]
        p[f"CAL_ACC{slot}_{a}SCALE"] = SCL[i]
        p[f"CAL_GYRO{slot}_{a}OFF"] = GOFF[i]
        p[f"SENS_BOARD_{a}_OFF"] = lvl[i]
    p.update(tc or {})
    return p


def _ap_params(orient=0, inst=0, tcal=None):
    nm = fc_params.names("ardupilot", inst)
    p = {"AHRS_ORIENTATION": orient, nm["accel_id"]: 1234, nm["gyro_id"]: 5678}
    for i in range(3):
        p[nm["accel_off"][i]] = OFF[i]
        p[nm["accel_scale"][i]] = SCL[i]
        p[nm["gyro_off"][i]] = GOFF[i]
    p.update(tcal or {})
    return p


def _source(fw, params, inst=0):
    return {"samples": "corrected", "firmware": fw, "format": "ulog" if fw == "px4" else
            "dataflash", "stream": "test", "instance": inst, "parameters": params,
            "parameters_changed": [], "device_ids": {"accel": 1234, "gyro": 5678}}


def _logged_fit(old_a, old_g):
    """The fit a perfect estimator makes of the logged data y = R S (x - o):
    y = b + K f_v with f_v = R f_s the specific force in the logged frame."""
    R, S, o = old_a.R, old_a.scale, old_a.offset
    b = R @ (S * (B0 - o))
    K = R @ np.diag(S) @ K0 @ R.T
    gb = old_g.R @ (D0 - old_g.offset)
    G = old_g.R @ G0 @ old_g.R.T
    return b, K, gb, G


def _as_dict(params):
    return dict(params)


@pytest.mark.parametrize("fw,rot", [("px4", r) for r in (0, 2, 4, 8, 16, 24, 30, 33)]
                         + [("ardupilot", r) for r in (0, 2, 6, 12, 25, 37, 41, 42)])
def test_composed_equals_the_absolute_calibration(fw, rot):
    """Composing the fit of corrected data with the parameters in force gives
    the sensor-frame calibration a raw fit gives (offsets B0, scales diag K0^-1),
    for every board rotation, PX4's level trims included: PX4's own update
    (Accelerometer.hpp BiasCorrectedSensorOffset) generalised."""
    lvl = (0.7, -1.2, 3.0) if fw == "px4" else (0, 0, 0)
    prm = _px4_params(rot, lvl) if fw == "px4" else _ap_params(rot)
    old_a = fc_params.in_force(fw, prm, "accel", 0, 1234 if fw == "px4" else None)
    old_g = fc_params.in_force(fw, prm, "gyro", 0, 5678 if fw == "px4" else None)
    b, K, gb, G = _logged_fit(old_a, old_g)
    params, notes, meta = autopilot_export(_cal(b, K, gb, G), fw, None, "c.h5",
                                           _source(fw, prm))
    got = _as_dict(params)
    nm = fc_params.names(fw, 0)
    k0inv = np.linalg.inv(K0)
    assert meta["mode"] == "composed" and notes[0].startswith("COMPOSED")
    assert np.allclose([got[k] for k in nm["accel_off"]], B0, rtol=0, atol=1e-12)
    assert np.allclose([got[k] for k in nm["accel_scale"]], np.diag(k0inv), rtol=0, atol=1e-12)
    assert np.allclose([got[k] for k in nm["gyro_off"]], D0, rtol=0, atol=1e-12)
    assert got[nm["accel_id"]] == 1234 and got[nm["gyro_id"]] == 5678
    # what is dropped is K0^-1's off-diagonal in the sensor frame, whatever the rotation
    drop = [v for k, v in meta["dropped"].items() if k.startswith("accel cross-axis")]
    off = k0inv - np.diag(np.diag(k0inv))
    assert drop and drop[0] == pytest.approx(np.abs(off).max(), rel=1e-9)


def _fw_px4_correct(prm, n, x, temp=None, sensor="accel"):
    """PX4's correction written out from its source (independent of calib's
    fc_params): Accelerometer.hpp Correct() = R ((x - thermal - offset) .* scale)
    with TemperatureCompensation.cpp calc_thermal_offsets_3D (rotation: none here)."""
    key = "ACC" if sensor == "accel" else "GYRO"
    off = np.array([prm[f"CAL_{key}{n}_{a}OFF"] for a in "XYZ"])
    scl = np.array([prm[f"CAL_ACC{n}_{a}SCALE"] for a in "XYZ"]) if sensor == "accel" \
        else np.ones(3)
    th = np.zeros_like(x)
    c = "A" if sensor == "accel" else "G"
    if prm.get(f"TC_{c}_ENABLE") == 1:
        j = next(j for j in range(4) if prm.get(f"TC_{c}{j}_ID") == prm[f"CAL_{key}{n}_ID"])
        tmin, tmax, tref = (prm[f"TC_{c}{j}_{k}"] for k in ("TMIN", "TMAX", "TREF"))
        for i, T in enumerate(temp):
            d = (tmax if T > tmax else tmin if T < tmin else T) - tref
            th[i] = [sum(prm[f"TC_{c}{j}_X{k}_{a}"] * d ** k for k in range(4)) for a in range(3)]
    return (x - th - off) * scl


def _fw_ap_correct(prm, x, temp=None):
    """ArduPilot's accelerometer correction written out from
    AP_InertialSensor_Backend.cpp _rotate_and_correct_accel (IMU 1, no rotation)
    and AP_InertialSensor_tempcal.cpp correct_accel (TEMP_REFERENCE 35, x 1e-6)."""
    off = np.array([prm[f"INS_ACCOFFS_{a}"] for a in "XYZ"])
    scl = np.array([prm[f"INS_ACCSCAL_{a}"] for a in "XYZ"])
    v = np.array(x, float)
    if prm.get("INS_TCAL1_ENABLE") == 1:
        tmin, tmax, ct = prm["INS_TCAL1_TMIN"], prm["INS_TCAL1_TMAX"], prm["INS_ACC1_CALTEMP"]
        c = [np.array([prm[f"INS_TCAL1_ACC{k}_{a}"] for a in "XYZ"]) for k in (1, 2, 3)]

        def P(T):
            d = min(max(T, tmin), tmax) - 35.0
            return (c[0] + (c[1] + c[2] * d) * d) * d * 1e-6

        v = v - np.array([P(T) for T in temp]) + P(ct)
    return (v - off) * scl


@pytest.mark.parametrize("fw", ["px4", "ardupilot"])
def test_thermal_export_through_the_firmware_equation(fw):
    """A bias drift (order 3, T_ref 25, fitted over 5..60 degC) exported as PX4's
    TC_A* / ArduPilot's INS_TCAL1_* removes calib's b + B(T) at every temperature
    of the range through the firmware's own formula; with a drift already in force
    the sum is exported."""
    coef = np.array([[2e-3, -4e-5, 3e-7], [-1e-3, 2e-5, 0.0], [5e-4, 0.0, -2e-7]])
    stats = {"temp_ref_degC": 25.0, "temp_range_degC": [5.0, 60.0]}
    cal = _cal(B0, np.eye(3), accel_temp_bias=coef, stats=stats)
    src = {"samples": "raw", "device_ids": {"accel": 1234}}  # sensor_accel of a ULog
    prm = dict(autopilot_export(cal, fw, 0, "c.h5", src)[0])
    T = np.linspace(5.0, 60.0, 12)
    want = B0 + temp_poly(coef, T - 25.0)
    x = np.zeros((len(T), 3))
    got = -(_fw_px4_correct(prm, 0, x, T) if fw == "px4" else _fw_ap_correct(prm, x, T))
    assert np.allclose(got, want, rtol=0, atol=1e-12)
    if fw == "px4":
        assert prm["TC_A_ENABLE"] == 1 and prm["TC_A0_TREF"] == 25.0
        assert prm["TC_A0_TMIN"] == 5.0 and prm["TC_A0_TMAX"] == 60.0 and prm["TC_A0_X0_0"] == 0


def test_px4_thermal_in_force_composes_with_a_fitted_drift():
    """TC_A0 in force (TREF 30 over 0..70 degC) and a residual drift fitted on the
    corrected data over 10..50 (T_ref 25): through PX4's formula, the exported
    offsets and polynomial remove what the ones in force removed plus the fitted
    residual brought back to the sensor frame, o + thermal(T) + S^-1 (b + B(T))."""
    tc = {"TC_A_ENABLE": 1, "TC_A0_ID": 1234, "TC_A0_TREF": 30.0, "TC_A0_TMIN": 0.0,
          "TC_A0_TMAX": 70.0}
    old_coef = np.array([[0.01, 1e-3, -2e-5, 1e-7], [0.0, -5e-4, 0.0, 0.0],
                         [0.02, 0.0, 1e-5, 0.0]])
    for k in range(4):
        for i in range(3):
            tc[f"TC_A0_X{k}_{i}"] = old_coef[i, k]
    prm = _px4_params(tc=tc)
    b_fit = np.array([3e-3, -2e-3, 1e-3])
    resid = np.array([[1e-4, 0, 0], [0, -2e-4, 1e-6], [3e-4, 0, 0]])
    cal = _cal(b_fit, np.diag(SCL) @ K0, accel_temp_bias=resid,
               stats={"temp_ref_degC": 25.0, "temp_range_degC": [10.0, 50.0]})
    new = dict(autopilot_export(cal, "px4", None, "c.h5", _source("px4", prm))[0])
    T = np.linspace(0.0, 70.0, 15)
    scale = np.array([new[f"CAL_ACC0_{a}SCALE"] for a in "XYZ"])
    removed_new = -_fw_px4_correct(new, 0, np.zeros((len(T), 3)), T) / scale
    removed_old = -_fw_px4_correct(prm, 0, np.zeros((len(T), 3)), T) / np.array(SCL)
    inside = (T >= 10.0) & (T <= 50.0)
    want = removed_old + (b_fit + temp_poly(resid, T - 25.0)) / np.array(SCL)
    assert np.allclose(removed_new[inside], want[inside], rtol=0, atol=1e-12)
    assert new["TC_A0_TREF"] == 30.0 and new["TC_A0_TMIN"] == 0.0 and new["TC_A0_TMAX"] == 70.0
    assert new["TC_A0_ID"] == 1234


def test_thermal_in_force_over_a_narrower_range_exits_4():
    tc = {"TC_A_ENABLE": 1, "TC_A0_ID": 1234, "TC_A0_TREF": 30.0, "TC_A0_TMIN": 20.0,
          "TC_A0_TMAX": 40.0, **{f"TC_A0_X{k}_{i}": 0.0 for k in range(4) for i in range(3)}}
    cal = _cal(B0, np.eye(3), accel_temp_bias=np.full((3, 1), 1e-4),
               stats={"temp_ref_degC": 25.0, "temp_range_degC": [10.0, 50.0]})
    with pytest.raises(EstimationError, match="20..40 degC"):
        autopilot_export(cal, "px4", None, "c.h5", _source("px4", _px4_params(tc=tc)))


def test_cannot_compose_exits_4():
    cal = _cal(B0, K0, D0, G0)
    for src, what in [
            ({**_source("px4", {}), "parameters": {}}, "no parameters"),
            ({**_source("px4", _px4_params()), "parameters_changed": ["CAL_ACC0_XOFF"]},
             "changed during the log"),
            (_source("px4", _px4_params(rot=37)), "SENS_BOARD_ROT = 37"),
            (_source("ardupilot", _ap_params(orient=100)), "AHRS_ORIENTATION = 100"),
            ({**_source("px4", _px4_params()), "device_ids": {}}, "does not say which"),
            (_source("ardupilot", _ap_params(tcal={"INS_TCAL1_ENABLE": 2})), "learning")]:
        with pytest.raises(EstimationError, match=what):
            autopilot_export(cal, src["firmware"], None, "c.h5", src)
    with pytest.raises(EstimationError, match="mix two firmwares"):
        autopilot_export(cal, "ardupilot", None, "c.h5", _source("px4", _px4_params()))
    # --residual writes the fit as it is, labelled
    params, notes, meta = autopilot_export(cal, "px4", None, "c.h5",
                                           {**_source("px4", {}), "parameters": {}},
                                           residual=True)
    assert meta["mode"] == "residual" and notes[0].startswith("RESIDUAL")
    assert dict(params)["CAL_ACC0_XOFF"] == B0[0]


EXPECTED = {("px4", 0): "CAL_ACC0_XOFF", ("px4", 3): "CAL_ACC3_XOFF",
            ("ardupilot", 0): "INS_ACCOFFS_X", ("ardupilot", 1): "INS_ACC2OFFS_X",
            ("ardupilot", 2): "INS_ACC3OFFS_X", ("ardupilot", 3): "INS4_ACCOFFS_X",
            ("ardupilot", 4): "INS5_ACCOFFS_X"}


def test_names_of_every_instance():
    """The names of PX4's Utilities.cpp (CAL_%s%u_%c%s) and of ArduPilot's
    AP_InertialSensor.cpp / AP_InertialSensor_Params.cpp parameter tables."""
    ap = {0: ("INS_ACCSCAL_X", "INS_GYROFFS_X", "INS_ACC_ID", "INS_GYR_ID", "INS_ACC1_CALTEMP",
              "INS_TCAL1_ACC1_X"),
          1: ("INS_ACC2SCAL_X", "INS_GYR2OFFS_X", "INS_ACC2_ID", "INS_GYR2_ID",
              "INS_ACC2_CALTEMP", "INS_TCAL2_ACC1_X"),
          2: ("INS_ACC3SCAL_X", "INS_GYR3OFFS_X", "INS_ACC3_ID", "INS_GYR3_ID",
              "INS_ACC3_CALTEMP", "INS_TCAL3_ACC1_X"),
          3: ("INS4_ACCSCAL_X", "INS4_GYROFFS_X", "INS4_ACC_ID", "INS4_GYR_ID",
              "INS4_ACC_CALTEMP", "INS4_TCAL_ACC1_X"),
          4: ("INS5_ACCSCAL_X", "INS5_GYROFFS_X", "INS5_ACC_ID", "INS5_GYR_ID",
              "INS5_ACC_CALTEMP", "INS5_TCAL_ACC1_X")}
    for n, want in ap.items():
        nm = fc_params.names("ardupilot", n)
        assert (nm["accel_scale"][0], nm["gyro_off"][0], nm["accel_id"], nm["gyro_id"],
                nm["accel_caltemp"], nm["accel_tc"]["coef"][0][0]) == want
        assert nm["accel_tc"]["enable"] == ("INS_TCAL%d_ENABLE" % (n + 1) if n < 3 else
                                            f"INS{n + 1}_TCAL_ENABLE")
    for n in range(4):
        nm = fc_params.names("px4", n)
        assert nm["accel_scale"][2] == f"CAL_ACC{n}_ZSCALE" and nm["gyro_id"] == f"CAL_GYRO{n}_ID"
        assert nm["accel_tc"]["coef"][3][2] == f"TC_A{n}_X3_2" and \
            nm["gyro_tc"]["tref"] == f"TC_G{n}_TREF"


@pytest.fixture(scope="module")
def cal_files(tmp_path_factory):
    from calib_cli.cli.main import main
    from calib_cli.io.h5 import write_calibration

    d = tmp_path_factory.mktemp("fcx")
    write_calibration(d / "c.h5", _cal(B0, K0, D0, G0))
    for args in (["simulate", "sample_data/rimu_six_position.toml", "--out", str(d / "r.h5")],
                 ["fit", "rimu", str(d / "r.h5"), "--out", str(d / "rimu.h5")]):
        with pytest.raises(SystemExit) as e:
            main(["-q", *args])
        assert e.value.code == 0
    return d


@pytest.mark.parametrize("fw,inst", [(f, i) for f in ("px4", "ardupilot")
                                     for i in (-1, 0, 1, 2, 3, 4, 5)])
def test_instance_names_or_exit_2(cal_files, run_cli, fw, inst):
    out = cal_files / f"o_{fw}_{inst}.txt"
    code, _, err = run_cli("export", cal_files / "c.h5", "--format", fw, "--instance", str(inst),
                           "--out", out)
    if (fw, inst) in EXPECTED or (fw == "px4" and 0 <= inst <= 3):
        assert code == 0, err
        want = EXPECTED.get((fw, inst), f"CAL_ACC{inst}_XOFF")
        assert want in out.read_text()
    else:
        assert code == 2 and not out.exists(), err
        assert ("0-3" if fw == "px4" else "0-4") in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("fw", ["px4", "ardupilot"])
def test_rimu_export_exits_3(cal_files, run_cli, fw):
    code, _, err = run_cli("export", cal_files / "rimu.h5", "--format", fw)
    assert code == 3 and "RIMU" in err and "c-header" in err, err
    assert len(err.strip().splitlines()) == 1


def test_gyro_dropped_label_names_g_inverse(cal_files, run_cli):
    code, out, _ = run_cli("export", cal_files / "c.h5", "--format", "px4")
    assert code == 0 and "off-diagonal of G^-1" in out and "off-diagonal of K^-1" in out
    rows = [r for r in csv.reader([ln for ln in out.splitlines() if not ln.startswith("#")],
                                  delimiter="\t")]
    assert all(len(r) == 5 for r in rows)


def test_in_force_file_round_trip(cal_files, run_cli, tmp_path):
    """--in-force reads a QGroundControl file (the format calib writes) and
    composes; a file of the other firmware is exit 3."""
    from calib_cli.io.export_autopilot import params_file

    f = tmp_path / "in_force.params"
    f.write_text(params_file(sorted(_px4_params().items()), ["in force"], "px4", "test"))
    fw, prm = fc_params.read_params_file(str(f))
    assert fw == "px4" and prm["CAL_ACC0_XSCALE"] == SCL[0] and prm["CAL_ACC0_ID"] == 1234
    code, out, err = run_cli("export", cal_files / "c.h5", "--format", "px4", "--in-force", f,
                             "--out", tmp_path / "o.params", "--json")
    assert code == 0, err
    meta = json.loads(out)["export"]
    assert meta["mode"] == "composed" and meta["in_force"]["CAL_ACC0_XOFF"] == OFF[0]
    code, _, err = run_cli("export", cal_files / "c.h5", "--format", "ardupilot", "--in-force", f)
    assert code == 3 and "px4 parameters" in err


def test_bad_options_and_counts(cal_files, run_cli):
    code, _, err = run_cli("export", cal_files / "c.h5", "--format", "json", "--residual")
    assert code == 2
    with pytest.raises(UsageProblem):
        autopilot_export(_cal(B0, K0), "px4", 7, "c.h5", {})
    with pytest.raises(InputError, match="unknown autopilot"):
        autopilot_export(_cal(B0, K0), "betaflight", 0, "c.h5", {})


def test_in_force_without_device_ids_uses_the_slot():
    """A hand-written parameter file without CAL_ACCn_ID: its slot (0, or
    --instance) is taken as the one in force."""
    prm = {k: v for k, v in _px4_params().items() if not k.endswith("_ID")}
    cal = _cal(np.zeros(3), np.eye(3), np.zeros(3), np.eye(3))
    got = dict(autopilot_export(cal, "px4", None, "c.h5", _source("px4", {}), in_force=prm)[0])
    assert got["CAL_ACC0_XOFF"] == OFF[0] and got["CAL_ACC0_YSCALE"] == SCL[1]
