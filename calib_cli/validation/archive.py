"""Simulated test archives for the batch tests and the benchmark.

make_archive(root, n, n_broken) writes ROOT/archive/<serial>/plan.toml and
recordings rec-NN.csv (or rec-NN.h5, every third one, raw already imported) of several units: even
units run a six-position plan with known attitudes (vector fit), odd units
hand-placed positions of unknown attitude (scalar fit). Each unit has one
fixed truth; every recording has its own noise. Broken files, in order:
a CSV with a text cell, an .h5 that is not HDF5, and a raw.h5 with too few
positions for its fit. Also writes ROOT/pipeline.toml.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

PIPELINE = """\
name = "archive-accel"
glob = ["**/*.csv", "**/*.h5"]

[[step]]
step = "import"
plan = "{dir}/plan.toml"

[[step]]
step = "fit"
method = "accel"
options = { method = "auto" }

[[step]]
step = "apply"

[[step]]
step = "export"
"""

_HEAD = """\
name = "{name}"
kind = "static"
sample_rate_hz = {fs}
transition_s = 1.0
[site]
latitude_deg = 50.45
height_m = 180.0
[unit]
serial = "{serial}"
"""

_SIX = [("z-up", [0, 0, 0]), ("z-down", [180, 0, 0]), ("x-up", [0, -90, 0]),
        ("x-down", [0, 90, 0]), ("y-up", [90, 0, 0]), ("y-down", [-90, 0, 0])]


def vector_plan(serial: str, n_pos: int = 6, fs: float = 50.0, dur: float = 3.0) -> str:
    text = _HEAD.format(name="six-position", fs=fs, serial=serial)
    for label, att in _SIX[:n_pos]:
        text += f"\n[[segment]]\nlabel = \"{label}\"\nattitude_deg = {att}\nduration_s = {dur}\n"
    return text


def scalar_plan(serial: str, n_pos: int = 10, fs: float = 50.0, dur: float = 3.0) -> str:
    return _HEAD.format(name="hand-placed", fs=fs, serial=serial) + (
        f"\n[[segment]]\nlabel = \"pos\"\nrepeat = \"auto\"\nsim_repeat = {n_pos}\n"
        f"duration_s = {dur}\n")


def unit_serial(u: int) -> str:
    return f"SN-{u + 1:04d}"


def write_recording(path: Path, plan_text: str, unit: int, seed: int, truth_scale=1.0) -> None:
    """Simulate one recording of unit ``unit`` (fixed truth) with noise ``seed``."""
    from calib_cli.io.csvlog import write_csv
    from calib_cli.io.h5 import write_raw
    from calib_cli.io.plan import parse_plan
    from calib_cli.model.truth import Truth, default_truth
    from calib_cli.sim.simulate import plan_layout, simulate

    plan = parse_plan(plan_text, str(path.parent / "plan.toml"))
    truth = default_truth(plan_layout(plan), np.random.default_rng(10_000 + unit))
    if truth_scale != 1.0:  # a unit that drifted: biases scaled
        params = dict(truth.params)
        params["accel_bias"] = params["accel_bias"] * truth_scale
        truth = Truth(truth.model, params, truth.noise)
    rec = simulate(plan, truth, seed)
    if path.suffix == ".csv":
        write_csv(path, rec)
    else:
        write_raw(path, rec)


def make_archive(root, n: int = 50, n_broken: int = 3, n_units: int = 4) -> dict:
    """Write the archive; returns {"pipeline", "archive", "good", "broken"} (paths)."""
    root = Path(root)
    arch = root / "archive"
    plans = {}
    for u in range(n_units):
        d = arch / unit_serial(u)
        d.mkdir(parents=True, exist_ok=True)
        text = vector_plan(unit_serial(u)) if u % 2 == 0 else scalar_plan(unit_serial(u))
        (d / "plan.toml").write_text(text)
        plans[u] = text
    good, broken = [], []
    for k in range(n):
        u = k % n_units
        d = arch / unit_serial(u)
        j = k // n_units
        kind_broken = k - (n - n_broken) if k >= n - n_broken else None
        ext = ".h5" if (j % 3 == 1 or kind_broken in (1, 2)) else ".csv"
        if kind_broken == 0:
            ext = ".csv"
        path = d / f"rec-{j + 1:02d}{ext}"
        if kind_broken is None:
            write_recording(path, plans[u], u, seed=k)
            good.append(str(path))
        elif kind_broken == 0:  # a CSV with a text cell in the data
            write_recording(path, plans[u], u, seed=k)
            lines = path.read_text().splitlines()
            cells = lines[10].split(",")
            cells[2] = "ERR"
            lines[10] = ",".join(cells)
            path.write_text("\n".join(lines) + "\n")
            broken.append(str(path))
        elif kind_broken == 1:  # not HDF5 at all
            path.write_bytes(b"\x89HDF\r\n garbage from a bad copy" + bytes(range(256)))
            broken.append(str(path))
        else:  # a valid raw.h5 with three positions: the fit cannot be made
            write_recording(path, vector_plan(unit_serial(u), n_pos=3), u, seed=k)
            broken.append(str(path))
    pipe = root / "pipeline.toml"
    pipe.write_text(PIPELINE)
    return {"pipeline": str(pipe), "archive": str(arch), "good": good, "broken": broken}
