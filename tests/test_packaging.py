"""The wheel ships every profile: pyproject's data-files cover profiles/ (a wheel
install finds them under <prefix>/share/calib/profiles, io.profiles.shipped_profiles)."""

from __future__ import annotations

import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_data_files_ship_every_profile():
    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    data = cfg["tool"]["setuptools"]["data-files"]
    shipped = set()
    for dest, patterns in data.items():
        assert dest.startswith("share/calib/profiles/")
        for pat in patterns:
            for f in ROOT.glob(pat):
                shipped.add((dest.removeprefix("share/calib/"), f.relative_to(ROOT).parent.as_posix()))
                shipped.add(f.relative_to(ROOT).as_posix())
    on_disk = {f.relative_to(ROOT).as_posix() for f in (ROOT / "profiles").rglob("*.toml")}
    assert on_disk and on_disk <= shipped
    # each destination mirrors its source directory
    assert all(d == s for d, s in (x for x in shipped if isinstance(x, tuple)))


def test_shipped_profiles_found_from_the_source_tree():
    from calib_cli.acquire.profile import load_imu_profile
    from calib_cli.io.profiles import list_rimu_profiles, shipped_profiles

    assert shipped_profiles() == ROOT / "profiles"
    assert "tetrahedron" in list_rimu_profiles()
    assert load_imu_profile("generic-bin6").name
