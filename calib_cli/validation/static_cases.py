"""Static plans for tests and benchmarks: twelve attitudes spread over the sphere."""

from __future__ import annotations

TWELVE = [[0, -90, 0], [0, 90, 0], [90, 0, 0], [-90, 0, 0], [0, 0, 0], [180, 0, 0],
          [45, 45, 0], [-45, 45, 30], [45, -45, 60], [135, 30, 10], [-135, -30, 80],
          [30, 60, 120]]


def static_plan_text(attitudes=TWELVE, duration=10.0, rate=100.0, known=True, serial="SN-T1",
                     lat=50.45, sigma_deg=None) -> str:
    lines = ["name = 'test'", "kind = 'static'", f"sample_rate_hz = {rate}",
             "transition_s = 3.0", "[site]", f"latitude_deg = {lat}", "height_m = 180.0",
             "[unit]", f"serial = '{serial}'"]
    for i, a in enumerate(attitudes):
        lines += ["[[segment]]", f"label = 'p{i + 1}'", f"duration_s = {duration}"]
        key = "attitude_deg" if known else "sim_attitude_deg"
        lines.append(f"{key} = {list(map(float, a))}")
        if sigma_deg is not None:
            lines.append(f"attitude_sigma_deg = {sigma_deg}")
    return "\n".join(lines) + "\n"
