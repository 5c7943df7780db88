"""The wheel ships every profile: pyproject's data-files cover profiles/ (a wheel
install finds them under <prefix>/share/calib/profiles, io.profiles.shipped_profiles)."""

from __future__ import annotations

import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_data_files_ship_every_profile():
    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    dest_of = {}  # profile file -> where the wheel installs it
    for dest, patterns in cfg["tool"]["setuptools"]["data-files"].items():
        for pat in patterns:
            for f in ROOT.glob(pat):
                dest_of[f.relative_to(ROOT).as_posix()] = dest
    on_disk = [f.relative_to(ROOT) for f in (ROOT / "profiles").rglob("*.toml")]
    assert on_disk
    for f in on_disk:  # every profile, under share/calib/ mirroring its directory
        assert dest_of.get(f.as_posix()) == "share/calib/" + f.parent.as_posix(), f


def test_shipped_profiles_found_from_the_source_tree():
    from calib_cli.acquire.profile import load_imu_profile
    from calib_cli.io.profiles import list_rimu_profiles, shipped_profiles

    assert shipped_profiles() == ROOT / "profiles"
    assert "tetrahedron" in list_rimu_profiles()
    assert load_imu_profile("generic-bin6").name
