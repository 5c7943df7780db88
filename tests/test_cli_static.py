"""The static slice end to end through the CLI, and every bad input of issue 2."""

import json

import h5py
import numpy as np
import pytest

from tests.conftest import TRUTH_SI, TWELVE, static_plan_text


def write_truth(path):
    p = TRUTH_SI["params"]
    path.write_text(
        "[params]\n"
        f"accel_bias = {p['accel_bias']}\naccel_K = {p['accel_K']}\ngyro_bias = {p['gyro_bias']}\n"
        "[noise]\naccel_white = 0.01\ngyro_white = 0.001\n")
    return path


@pytest.fixture
def plan(tmp_path):
    p = tmp_path / "plan.toml"
    p.write_text(static_plan_text(duration=8.0))
    return p


def outputs(tmp_path):
    return sorted(x.name for x in tmp_path.iterdir())


def test_round_trip_csv_import_fit_apply(tmp_path, plan, run_cli):
    truth = write_truth(tmp_path / "truth.toml")
    csv = tmp_path / "log.csv"
    code, _, err = run_cli("simulate", plan, "--out", csv, "--seed", "4", "--truth", truth)
    assert code == 0, err
    header = [ln for ln in csv.read_text().splitlines() if not ln.startswith("#")][0]
    assert header.split(",")[:7] == ["time", "ax", "ay", "az", "gx", "gy", "gz"]
    # once with the segment column, once without (static detection)
    lines = csv.read_text().splitlines()
    nocol = tmp_path / "noseg.csv"
    nocol.write_text("\n".join(",".join(ln.split(",")[:-1]) if not ln.startswith("#") else ln
                               for ln in lines) + "\n")
    for src in (csv, nocol):
        raw, cal, cor = tmp_path / "raw.h5", tmp_path / "cal.h5", tmp_path / "cor.h5"
        assert run_cli("import", "csv", src, "--plan", plan, "--out", raw)[0] == 0
        assert run_cli("fit", "accel", raw, "--out", cal)[0] == 0
        assert run_cli("apply", cal, raw, "--out", cor)[0] == 0
        code, out, _ = run_cli("show", cal, "--json")
        obj = json.loads(out)
        assert obj["method"] == "vector" and obj["unit"]["serial"] == "SN-T1"
        assert set(obj) >= {"method", "unit", "params", "sigma", "units", "stats"}
        assert obj["units"]["accel_K"] == "-" and obj["units"]["accel_bias"] == "m/s^2"
        st = obj["stats"]
        assert st["unobservable"] == [] and st["accel_residual_rms"] > 0
        from calib_cli.io.h5 import read_raw

        c = read_raw(cor, kinds=("corrected",))
        g = 9.810547697  # not used directly: compare with the file's site gravity
        g = c.site.gravity
        for s in c.static_segments():
            x = c.accel[s.slice]
            err = np.linalg.norm(x.mean(0)) - g
            # within 4.5 sigma of the mean's noise (0.01 / sqrt(n)) plus the fit's own error
            assert abs(err) < 4.5 * (0.01 / np.sqrt(len(x))) * 1.5, (s.label, err)
        with h5py.File(cor) as h5:
            assert h5.attrs["kind"].decode() == "corrected"
            assert "input_sha256" in h5.attrs and str(cal) in h5.attrs["input_sha256"].decode()
    code, out, _ = run_cli("show", cal, "--json", "--covariance")
    cov = json.loads(out)["covariance"]
    assert len(cov["order"]) == 12 and np.array(cov["matrix"]).shape == (12, 12)


def bad_csv(tmp_path, body, name="bad.csv"):
    p = tmp_path / name
    p.write_text(body)
    return p


GOOD_HEAD = "time,ax,ay,az,gx,gy,gz\n"


@pytest.mark.parametrize("body,needle", [
    ("time,ax,ay,gx,gy,gz\n0,1,2,3,4,5\n", "missing column az"),
    (GOOD_HEAD + "0,1,2,3,4,5,6\n0.01,1,x2,3,4,5,6\n", "not a number"),
    (GOOD_HEAD + "0,1,2,3,4,5,6\n0.01,1,nan,3,4,5,6\n", "NaN"),
    (GOOD_HEAD + "0,1,2,3,4,5,6\n0,1,2,3,4,5,6\n", "not increasing"),
    ("", "empty file"),
    ("# only a comment\n", "empty file"),
    (GOOD_HEAD, "no data rows"),
])
def test_bad_csv_exit_3_one_line_no_output(tmp_path, plan, run_cli, body, needle):
    csv = bad_csv(tmp_path, body)
    out = tmp_path / "raw.h5"
    code, _, err = run_cli("import", "csv", csv, "--plan", plan, "--out", out)
    assert code == 3
    lines = err.strip().splitlines()
    assert len(lines) == 1 and str(csv) in lines[0] and needle in lines[0], err
    assert not out.exists() and outputs(tmp_path) == sorted(["bad.csv", "plan.toml"])


@pytest.mark.parametrize("text,needle", [
    ("kind = 'banana'\n[[segment]]\nlabel='a'\n", "unknown plan kind"),
    ("kind = 'static'\n", "no [[segment]]"),
    ("kind = 'static'\n[[segment]]\nattitude_deg = [1, 2]\n", "attitude_deg"),
    ("kind = [\n", "not valid TOML"),
])
def test_bad_plan_exit_3(tmp_path, run_cli, text, needle):
    p = tmp_path / "plan.toml"
    p.write_text(text)
    out = tmp_path / "r.h5"
    code, _, err = run_cli("simulate", p, "--out", out)
    assert code == 3 and needle in err and str(p) in err and len(err.strip().splitlines()) == 1
    assert not out.exists()


def test_detected_positions_do_not_match_plan(tmp_path, run_cli):
    # simulate 12 positions, import with a plan of 11: exit 3 naming both counts
    p12 = tmp_path / "p12.toml"
    p12.write_text(static_plan_text(duration=5.0))
    p11 = tmp_path / "p11.toml"
    p11.write_text(static_plan_text(TWELVE[:11], duration=5.0))
    csv = tmp_path / "log.csv"
    assert run_cli("simulate", p12, "--out", csv)[0] == 0
    lines = csv.read_text().splitlines()
    csv.write_text("\n".join(",".join(ln.split(",")[:-1]) if not ln.startswith("#") else ln
                             for ln in lines) + "\n")
    out = tmp_path / "r.h5"
    code, _, err = run_cli("import", "csv", csv, "--plan", p11, "--out", out)
    assert code == 3 and "detected 12 static intervals" in err and "11 static" in err
    assert not out.exists()


def test_wrong_kind_and_version_exit_3(tmp_path, plan, run_cli):
    raw = tmp_path / "raw.h5"
    assert run_cli("simulate", plan, "--out", raw)[0] == 0
    out = tmp_path / "x.h5"
    code, _, err = run_cli("apply", raw, raw, "--out", out)  # a raw file where a calibration goes
    assert code == 3 and "expected 'calibration'" in err and not out.exists()
    with h5py.File(raw, "a") as h5:
        h5.attrs["format_version"] = 99
    code, _, err = run_cli("fit", "accel", raw, "--out", out)
    assert code == 3 and "format version" in err and not out.exists()
    junk = tmp_path / "junk.h5"
    junk.write_bytes(b"not hdf5 at all")
    code, _, err = run_cli("show", junk)
    assert code == 3 and "not an HDF5 file" in err


def test_too_few_and_degenerate_exit_4(tmp_path, run_cli):
    for atts, needle in ((TWELVE[:3], ">= 4 static positions"), ([[5, 5, 5]] * 6, "span 3-D")):
        p = tmp_path / "plan.toml"
        p.write_text(static_plan_text(atts, duration=3.0))
        raw, cal = tmp_path / "raw.h5", tmp_path / "cal.h5"
        assert run_cli("simulate", p, "--out", raw)[0] == 0
        code, _, err = run_cli("fit", "accel", raw, "--out", cal)
        assert code == 4 and needle in err and len(err.strip().splitlines()) == 1
        assert not cal.exists()


def test_usage_error_exit_2(run_cli):
    code, _, _ = run_cli("fit", "accel")
    assert code == 2


def test_repeat_auto_absorbs_hand_placed_positions(tmp_path, run_cli):
    """An initial static period plus any number of hand-placed positions,
    detected without a segment column, then fitted by the scalar method."""
    plan = tmp_path / "hand.toml"
    plan.write_text("kind = 'static'\nsample_rate_hz = 100\ntransition_s = 2.5\n"
                    "[site]\nlatitude_deg = 45\n"
                    "[[segment]]\nlabel = 'init'\nduration_s = 20\nsim_attitude_deg = [1, 2, 3]\n"
                    "[[segment]]\nlabel = 'hand'\nrepeat = 'auto'\nsim_repeat = 15\nduration_s = 4\n")
    csv = tmp_path / "log.csv"
    assert run_cli("simulate", plan, "--out", csv, "--seed", "3")[0] == 0
    lines = csv.read_text().splitlines()
    csv.write_text("\n".join(",".join(ln.split(",")[:-1]) if not ln.startswith("#") else ln
                             for ln in lines) + "\n")
    raw, cal = tmp_path / "raw.h5", tmp_path / "cal.h5"
    code, _, err = run_cli("import", "csv", csv, "--plan", plan, "--out", raw)
    assert code == 0, err
    code, out, _ = run_cli("show", raw, "--json")
    segs = json.loads(out)["segments"]
    assert [s["label"] for s in segs] == ["init"] + [f"hand#{k}" for k in range(1, 16)]
    assert all(s["attitude"] is None for s in segs)
    code, _, err = run_cli("fit", "accel", raw, "--out", cal)
    assert code == 0, err
    code, out, _ = run_cli("show", cal, "--json")
    assert json.loads(out)["method"] == "scalar"
