"""HDF5 files written by calib 0.1.0 (tests/fixtures/v0.1.0, make_fixtures.sh) stay
readable: raw, calibration and corrected files of a triad and a redundant unit."""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np
import pytest

from calib_cli.io.apply_file import apply_file
from calib_cli.io.contract_json import calibration_json, to_jsonable
from calib_cli.io.h5 import read_calibration, read_raw

FIX = Path(__file__).parent / "fixtures" / "v0.1.0"


@pytest.mark.parametrize("name", ["raw_static.h5", "raw_rimu.h5"])
def test_raw_files_read(name):
    rec = read_raw(FIX / name)
    assert len(rec) > 100 and rec.accel.shape[1] == rec.layout.n
    assert len(rec.segments) >= 6
    with h5py.File(FIX / name) as h5:  # written by calib 0.1.0, file format 1
        assert h5.attrs["tool_version"] == "0.1.0" and int(h5.attrs["format_version"]) == 1


@pytest.mark.parametrize("name", ["cal_accel", "cal_rimu"])
def test_calibrations_read_as_written(name):
    want = json.loads((FIX / f"{name}.json").read_text())
    got = json.loads(json.dumps(to_jsonable(calibration_json(FIX / f"{name}.h5"))))
    assert got["method"] == want["method"] and got["unit"] == want["unit"]
    assert got["units"] == want["units"] and set(got["params"]) == set(want["params"])
    for k, v in want["params"].items():
        np.testing.assert_allclose(np.asarray(got["params"][k], float), np.asarray(v, float),
                                   rtol=0, atol=0)
    raw = FIX / ("raw_static.h5" if name == "cal_accel" else "raw_rimu.h5")
    assert read_calibration(FIX / f"{name}.h5").layout.n == read_raw(raw).layout.n


def test_apply_reproduces_the_corrected_file(tmp_path):
    out = tmp_path / "corrected.h5"
    apply_file(FIX / "cal_accel.h5", FIX / "raw_static.h5", out)
    new, old = read_raw(out, kinds=("corrected",)), read_raw(FIX / "corrected_static.h5",
                                                            kinds=("corrected",))
    np.testing.assert_allclose(new.accel, old.accel, rtol=0, atol=1e-12)
    np.testing.assert_allclose(new.gyro, old.gyro, rtol=0, atol=1e-12)


def test_rimu_calibration_applies(tmp_path):
    out = tmp_path / "corrected.h5"
    apply_file(FIX / "cal_rimu.h5", FIX / "raw_rimu.h5", out)
    with h5py.File(out) as h5:
        assert h5["samples/accel_body"].shape[1] == 3
