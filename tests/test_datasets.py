"""The issue-6 comparisons on real recordings (docs/validation/datasets.md).

Datasets live at <repo>/../shared/datasets (CI clones the repo with shared/
beside it); CALIB_DATASETS overrides the location.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from calib_cli.validation import validate_datasets as vd

ROOT = Path(os.environ.get("CALIB_DATASETS",
                           Path(__file__).resolve().parents[2] / "shared" / "datasets"))
needs_xsens = pytest.mark.skipif(not (ROOT / "imu_tk_xsens_mti" / "xsens_acc.mat").exists(),
                                 reason=f"Xsens dataset not found under {ROOT}")
needs_imucal = pytest.mark.skipif(
    not (ROOT / "imucal_ferraris" / "annotated_session.csv").exists(),
    reason=f"imucal dataset not found under {ROOT}")


@pytest.fixture(scope="module")
def xsens():
    return vd.xsens(ROOT)


@pytest.fixture(scope="module")
def ferraris():
    return vd.ferraris_annotated(ROOT)


def test_lower_times_rotation():
    rng = np.random.default_rng(0)
    K = np.diag([400.0, 410, 420]) @ (np.eye(3) + 0.02 * rng.standard_normal((3, 3)))
    L, Q = vd.lower_times_rotation(K)
    assert np.allclose(L @ Q, K) and np.allclose(np.triu(L, 1), 0)
    assert np.allclose(Q @ Q.T, np.eye(3)) and np.linalg.det(Q) > 0 and np.all(np.diag(L) > 0)


@needs_xsens
def test_xsens_accel_g_rms_not_worse_than_imutk(xsens):
    assert len(xsens["windows"]) == 38
    assert xsens["n_params_ours"] == xsens["n_params_imutk"] == 9
    assert xsens["g_rms_ours"] <= xsens["g_rms_imutk"]
    assert xsens["g_rms_ours"] < 1.2e-3


@needs_xsens
def test_xsens_scale_factors_within_half_percent(xsens):
    assert np.all(np.abs(xsens["acc_scale_rel"]) < 0.005), xsens["acc_scale"]
    assert np.all(np.abs(xsens["gyro_scale_rel"]) < 0.005), xsens["gyro_scale"]


@needs_xsens
def test_xsens_misalignments_within_0_01(xsens):
    assert xsens["acc_mis_maxdiff"] < 0.01
    assert xsens["gyro_mis_maxdiff"] < 0.01
    # the comparison is not vacuous: the manufacturer's misalignments are of that size
    assert np.abs(xsens["gyro_mis_man"] - np.eye(3)).max() > 0.02


@needs_imucal
def test_ferraris_scale_factors_within_half_percent_of_imucal(ferraris):
    assert np.all(np.abs(ferraris["acc_scale_rel"]) < 0.005), ferraris["acc_scale"]
    assert np.all(np.abs(ferraris["gyro_scale_rel"]) < 0.005), ferraris["gyro_scale_dps"]
    assert ferraris["accel_method"] == "vector"


@needs_imucal
def test_ferraris_conventions(ferraris):
    # the raw gyro turns +360 deg with positive scale factors; imucal's own
    # parameters (expected_angle -360) turn it -360 deg
    for ang in ferraris["raw_turn_deg"].values():
        assert abs(ang - 360.0) < 1.0
    for ang in ferraris["imucal_turn_deg"].values():
        assert abs(ang + 360.0) < 1.0
    # our G = -(K_g R_g) * 180/pi, entry by entry (counts/(rad/s))
    assert np.allclose(ferraris["gyro_K"], ferraris["gyro_K_ref"], atol=1.0)
    assert np.allclose(ferraris["accel_K"], ferraris["accel_K_ref"], atol=0.3)
    assert np.allclose(ferraris["gyro_bias"], ferraris["gyro_bias_ref"], atol=0.1)


@needs_imucal
def test_ferraris_example_session_sign_from_transitions():
    ex = vd.ferraris_example(ROOT)
    m, p = ex[-360.0], ex[360.0]
    assert m["stats"]["n_transitions"] == 5 and m["stats"]["n_turns"] == 3
    assert np.all(np.abs(np.diag(m["gyro_K"]) - 1) < 0.05)
    # the wrong sign contradicts the recorded transitions
    wrong, right = (x["stats"]["transition_residual_rms_rad"] for x in (p, m))
    assert wrong > 20 * right


@pytest.mark.slow
@needs_xsens
@needs_imucal
def test_write_validation_md():
    """make validate: regenerate docs/validation/datasets.md."""
    out = Path(__file__).resolve().parents[1] / "docs" / "validation" / "datasets.md"
    out.parent.mkdir(exist_ok=True)
    text = vd.markdown(ROOT)
    out.write_text(text, encoding="utf-8")
    assert "Xsens" in text and "imucal" in text


@needs_xsens
def test_xsens_import_text_cli(tmp_path, capsys):
    """The documented command line (docs/import.md) on imu_tk's files."""
    from test_gyro_fit import run_cli

    from calib_cli.io.h5 import read_raw

    d = ROOT / "imu_tk_xsens_mti"
    plan = tmp_path / "xsens.toml"
    plan.write_text(vd.XSENS_PLAN)
    code, _, err = run_cli(["-q", "import", "text", str(d / "xsens_acc.mat"),
                            str(d / "xsens_gyro.mat"), "--plan", str(plan), "--out",
                            str(tmp_path / "xs.h5"), "--accel-units", "count", "--gyro-units",
                            "count"], capsys)
    assert code == 0, err
    rec = read_raw(tmp_path / "xs.h5")
    assert rec.units == {"accel": "count", "gyro": "count"}
    assert len(rec.static_segments()) == 38 and len(rec) == 51175
