"""Plans written by hand from CONTRACT.md alone, shared by the robustness tests
(issue 37): a six-position static plan and an 18-position RIMU plan."""

from __future__ import annotations

import random
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

SIX_POSITIONS = (("x-up", [0, -90, 0]), ("x-down", [0, 90, 0]), ("y-up", [90, 0, 0]),
                 ("y-down", [-90, 0, 0]), ("z-up", [0, 0, 0]), ("z-down", [180, 0, 0]))


def six_position_plan(name: str, serial: str, rate_hz: float = 50.0,
                      duration_s: float = 3.0) -> str:
    """A static plan: six positions, each sensor axis up and down, at Kyiv's site."""
    return f"""name = "{name}"
kind = "static"
sample_rate_hz = {rate_hz:.1f}
transition_s = 1.0
[site]
latitude_deg = 50.45
height_m = 180.0
[unit]
serial = "{serial}"
""" + "".join(f"""[[segment]]
label = "{lab}"
attitude_deg = {att}
duration_s = {duration_s:.1f}
""" for lab, att in SIX_POSITIONS)


def rimu18_plan() -> str:
    """The shipped RIMU plan's positions three times (18 rotating segments) at
    random attitudes, 3 s each (the constraint count of issue 37, point 11)."""
    text = (ROOT / "sample_data" / "plans" / "rimu.toml").read_text()
    head, segs = text.split("[[segment]]", 1)
    blocks = ["[[segment]]" + b for b in ("[[segment]]" + segs).split("[[segment]]")[1:]]
    rng = random.Random(4)
    text = head + "".join(b.replace('label = "', f'label = "r{k}-') for k in range(3)
                          for b in blocks)
    text = re.sub(r"attitude_deg = \[[^\]]*\]", lambda m: (
        f"attitude_deg = [{rng.uniform(-170, 170):.1f}, {rng.uniform(-80, 80):.1f}, "
        f"{rng.uniform(-170, 170):.1f}]"), text)
    return text.replace("duration_s = 10.0", "duration_s = 3.0")
