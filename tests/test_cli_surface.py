"""The CLI without surprises: --json on every fit prints the contract object
and nothing else on stdout; -q anywhere; calib profiles lists the search path;
completion of profile names."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest
from click.testing import CliRunner

from calib_cli.cli.main import cli

CONTRACT_KEYS = {"method", "unit", "params", "sigma", "units", "stats"}


def _runner():
    try:
        return CliRunner(mix_stderr=False)
    except TypeError:  # click >= 8.2: stderr is always separate
        return CliRunner()


@pytest.fixture(scope="module")
def raws(tmp_path_factory):
    d = tmp_path_factory.mktemp("surface")
    r = _runner()
    for m, extra in (("static", []), ("ferraris", []), ("align", ["--duration", "30"]),
                     ("rimu", [])):
        assert r.invoke(cli, ["-q", "plan", "make", m, *extra, "--out", str(d / f"{m}.toml")]
                        ).exit_code == 0
        res = r.invoke(cli, ["-q", "simulate", str(d / f"{m}.toml"), "--out",
                             str(d / f"{m}.h5"), "--seed", "2"])
        assert res.exit_code == 0, res.output
    return d


@pytest.mark.parametrize("method,raw", [("accel", "static"), ("gyro", "ferraris"),
                                        ("align", "align"), ("rimu", "rimu")])
def test_fit_json_is_the_contract_object_alone(raws, method, raw):
    r = _runner().invoke(cli, ["fit", method, str(raws / f"{raw}.h5"), "--out",
                               str(raws / f"{method}.json.h5"), "--json"])
    assert r.exit_code == 0, r.output
    obj = json.loads(r.stdout)  # the whole of stdout is one JSON object
    assert CONTRACT_KEYS <= set(obj)
    assert "stats" in obj and "unobservable" in obj["stats"]
    assert (raws / f"{method}.json.h5").is_file()


def test_quiet_after_the_subcommand(raws):
    r = _runner().invoke(cli, ["fit", "accel", str(raws / "static.h5"), "--out",
                               str(raws / "q.h5"), "-q"])
    assert r.exit_code == 0, r.output
    assert r.stdout == "" and (r.stderr or "") == ""
    r = _runner().invoke(cli, ["fit", "accel", str(raws / "static.h5"), "--quiet", "--out",
                               str(raws / "q2.h5")])
    assert r.exit_code == 0 and (r.stderr or "") == ""


def test_profiles_lists_user_then_shipped(tmp_path, monkeypatch):
    (tmp_path / "imu").mkdir()
    (tmp_path / "imu" / "bench.toml").write_text('description = "the bench unit"\n')
    (tmp_path / "imu" / "nmea-imu.toml").write_text("# my own nmea-imu\n")
    monkeypatch.setenv("CALIB_PROFILE_PATH", str(tmp_path))
    r = _runner().invoke(cli, ["profiles", "--json"])
    assert r.exit_code == 0, r.output
    rows = json.loads(r.stdout)
    by = {(p["kind"], p["name"]): p for p in rows}
    assert by[("imu", "bench")]["description"] == "the bench unit"
    assert by[("imu", "nmea-imu")]["source"] == "CALIB_PROFILE_PATH"  # shadows the shipped one
    assert ("rimu", "tetrahedron") in by and ("turntable", "manual") in by
    assert all(p["description"] for p in rows if p["source"] == "shipped")
    from calib_cli.acquire.profile import resolve_profile

    assert resolve_profile("bench", "imu") == str(tmp_path / "imu" / "bench.toml")
    r = _runner().invoke(cli, ["profiles", "--all", "--kind", "imu", "--json"])
    assert any(p["shadowed"] and p["name"] == "nmea-imu" for p in json.loads(r.stdout))


def test_completion_of_profile_names():
    env = dict(os.environ, COMP_WORDS="calib record --imu nm", COMP_CWORD="3",
               _CALIB_COMPLETE="bash_complete")
    out = subprocess.run([sys.executable, "-c", "from calib_cli.cli.main import cli; cli(prog_name='calib')"],
                         env=env, capture_output=True, text=True, timeout=60)
    assert "nmea-imu" in out.stdout
