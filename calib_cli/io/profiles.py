"""Geometry profiles of redundant units (``profiles/rimu/NAME.toml``).

A plan of kind "rimu" may write ``[rimu] profile = "tetrahedron"`` instead of
its own ``el0_deg``/``az0_deg`` lists. The name is looked up as

1. a path (absolute, or relative to the plan file's directory), when it
   names an existing file or ends in ``.toml``;
2. ``rimu/NAME.toml`` along the profile search path (``profile_dirs()``:
   ``$CALIB_PROFILE_PATH``, ``~/.config/calib/profiles``, then the shipped
   profiles -- the repository's top-level ``profiles`` directory, or where a
   wheel installed them).

A profile file holds ``el0_deg`` and ``az0_deg`` (degrees, one entry per
sensor, taken modulo 360) and optional ``name``/``description``/``sensors``.
"""

from __future__ import annotations

import sys
import tomllib
from pathlib import Path

from calib_cli.errors import InputError


def shipped_profiles() -> Path:
    """The directory of the shipped profiles: ``profiles/`` beside the package in a
    source tree (editable install), else ``<prefix>/share/calib/profiles`` where a
    wheel puts them (pyproject.toml, data-files)."""
    src = Path(__file__).resolve().parents[2] / "profiles"
    if src.is_dir():
        return src
    return Path(sys.prefix) / "share" / "calib" / "profiles"


PROFILE_DIR = shipped_profiles() / "rimu"

KINDS = ("imu", "turntable", "rimu", "chamber")
USER_DIR = Path("~/.config/calib/profiles")


def profile_dirs() -> list[tuple[str, Path]]:
    """Where a profile NAME is looked up, first match wins: each directory of
    ``$CALIB_PROFILE_PATH`` (os.pathsep-separated), then
    ``~/.config/calib/profiles``, then the shipped profiles. Each holds
    ``imu/``, ``turntable/`` and ``rimu/`` subdirectories of ``NAME.toml``."""
    import os

    out = [("CALIB_PROFILE_PATH", Path(d).expanduser())
           for d in os.environ.get("CALIB_PROFILE_PATH", "").split(os.pathsep) if d.strip()]
    out.append(("user", USER_DIR.expanduser()))
    out.append(("shipped", shipped_profiles()))
    return out


def find_profile(name: str, kind: str) -> Path | None:
    """The first ``KIND/NAME.toml`` along ``profile_dirs()``, or None."""
    for _, d in profile_dirs():
        f = d / kind / f"{name}.toml"
        if f.is_file():
            return f
    return None


def describe(path: Path) -> str:
    """A profile's one-line description: its ``description`` key, else its first
    comment line."""
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError):
        return "(unreadable)"
    try:
        raw = tomllib.loads(text)
        d = raw.get("description") or (raw.get("rimu") or {}).get("description")
        if isinstance(d, str) and d.strip():
            return " ".join(d.split())
    except tomllib.TOMLDecodeError:
        return "(not valid TOML)"
    for line in text.splitlines():
        if line.startswith("#") and line.strip("# ").strip():
            return line.strip("# ").strip()
    return ""


def all_profiles(kinds=KINDS) -> list[dict]:
    """Every profile along the search path: {kind, name, source, path,
    description, shadowed} (shadowed: an earlier directory has the same name)."""
    seen = set()
    out = []
    for source, d in profile_dirs():
        for kind in kinds:
            for f in sorted((d / kind).glob("*.toml")) if (d / kind).is_dir() else []:
                key = (kind, f.stem)
                out.append({"kind": kind, "name": f.stem, "source": source, "path": str(f),
                            "description": describe(f), "shadowed": key in seen})
                seen.add(key)
    return out


def _candidates(name: str, plan_path: str) -> list[Path]:
    out = []
    base = Path(plan_path).parent if plan_path and not plan_path.startswith("<") else Path(".")
    p = Path(name)
    out.append(p if p.is_absolute() else base / p)
    if not name.endswith(".toml") and "/" not in name and "\\" not in name:
        out.append(find_profile(name, "rimu") or PROFILE_DIR / f"{name}.toml")
    return out


def list_rimu_profiles() -> list[str]:
    """Names of the profiles shipped in profiles/rimu/."""
    return sorted(p.stem for p in PROFILE_DIR.glob("*.toml")) if PROFILE_DIR.is_dir() else []


def load_rimu_profile(name, plan_path: str = "<plan>") -> dict:
    """The ``[rimu]`` table (el0_deg, az0_deg lists) of profile ``name``.

    Raises InputError naming the plan when the profile is not found, or the
    profile file when it is malformed.
    """
    if not isinstance(name, str) or not name:
        raise InputError(f"rimu.profile must be a non-empty string, got {name!r}", plan_path)
    found = next((c for c in _candidates(name, plan_path) if c.is_file()), None)
    if found is None:
        known = ", ".join(list_rimu_profiles()) or "none"
        raise InputError(f"rimu profile {name!r} not found (shipped profiles: {known}; or give "
                         "a path relative to the plan)", plan_path)
    try:
        raw = tomllib.loads(found.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise InputError(f"cannot read rimu profile: {exc}", str(found)) from None
    from calib_cli.io.schema import RIMU_PROFILE, strict_keys  # issue 15: strict

    strict_keys(raw, RIMU_PROFILE[""] | {"rimu"}, str(found))
    table = raw.get("rimu", raw)
    if isinstance(table, dict) and table is not raw:
        strict_keys(table, RIMU_PROFILE[""], str(found), "[rimu] ")
    if not isinstance(table, dict) or "el0_deg" not in table or "az0_deg" not in table:
        raise InputError("a rimu profile needs el0_deg and az0_deg lists", str(found))
    return {"el0_deg": table["el0_deg"], "az0_deg": table["az0_deg"]}
