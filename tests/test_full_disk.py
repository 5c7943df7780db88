"""Issue 37: a full disk (0 B, 4 kB, 20 kB, 300 kB, 3 MB free, on a small tmpfs)
for import, simulate, fit, recover, diagnose, batch, apply, report and record:
exit 0 with a complete output, or exit 2 with one line naming the output and
nothing left behind (no temp or lock file), never a signal; record keeps its
journal when it recorded something. Needs root (mount); skipped otherwise.

Each size runs in one child process (``_driver``) that mounts a fresh tmpfs per
command and runs the commands in-process, so a signal (the segmentation fault
HDF5 used to end in) kills the child and fails the test."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.hand_plans import six_position_plan

ROOT = Path(__file__).resolve().parents[1]
SIZES = {"0B": 0, "4kB": 4 << 10, "20kB": 20 << 10, "300kB": 300 << 10, "3MB": 3 << 20}

pytestmark = pytest.mark.skipif(
    not hasattr(os, "geteuid") or os.geteuid() != 0 or shutil.which("mount") is None,
    reason="mounting a tmpfs needs root")

PLAN = six_position_plan("fd", "SN-FULL", rate_hz=100.0, duration_s=25.0)

_DRIVER = r'''
import contextlib, io, json, os, subprocess, sys, time
from pathlib import Path
d, size = Path(sys.argv[1]), int(sys.argv[2])
from calib_cli.cli.main import main

def mount(m):
    m.mkdir(exist_ok=True)
    subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size or 64 << 10}", "tmpfs", str(m)],
                   check=True)
    if size == 0:  # 0 B free: fill a small one
        fd = os.open(m / "filler", os.O_WRONLY | os.O_CREAT)
        with contextlib.suppress(OSError):
            while True:
                os.write(fd, b"\0" * 4096)
        os.close(fd)

def run(name, args, record=False):
    m = d / f"m-{name}"
    try:
        mount(m)
        return measure(name, args, m)
    finally:
        if subprocess.run(["umount", str(m)], check=False).returncode:
            subprocess.run(["umount", "-l", str(m)], check=False)
        with contextlib.suppress(OSError):
            m.rmdir()

def measure(name, args, m):
    before = sorted(os.listdir(m))
    err = io.StringIO()
    code = 0
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            main(["-q", *[str(a).replace("FULL", str(m)) for a in args]])
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else 0
    left = sorted(set(os.listdir(m)) - set(before))
    files = {}
    for root, _, names in os.walk(m):
        for n in names:
            p = os.path.join(root, n)
            files[os.path.relpath(p, m)] = os.path.getsize(p)
    return {"name": name, "code": code, "err": err.getvalue(), "left": left, "files": files}

out = []
emu = None
for name, args in json.loads(sys.argv[3]):
    if name == "record":
        from calib_cli.acquire.emulator import Emulator
        from calib_cli.acquire.profile import load_imu_profile
        if emu is None:
            (d / "emu").mkdir(exist_ok=True)
            emu = Emulator(load_imu_profile("generic-bin6"), None, rate=1000,
                           link_dir=str(d / "emu")).start()
            time.sleep(0.5)
    out.append(run(name, args))
if emu is not None:
    emu.stop()
print(json.dumps(out))
'''


def _cli(*args):
    from calib_cli.cli.main import main

    try:
        main(["-q", *[str(a) for a in args]])
    except SystemExit as exc:
        return exc.code
    return 0


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    d = tmp_path_factory.mktemp("fullin")
    (d / "plan.toml").write_text(PLAN)
    assert _cli("simulate", d / "plan.toml", "--out", d / "log.csv", "--seed", "5") == 0
    assert _cli("import", "csv", d / "log.csv", "--plan", d / "plan.toml", "--out",
                d / "raw.h5") == 0
    assert _cli("fit", "accel", d / "raw.h5", "--out", d / "cal.h5") == 0
    (d / "arch").mkdir()
    shutil.copy(d / "raw.h5", d / "arch" / "r.h5")
    (d / "pipe.toml").write_text('name = "p"\n[[step]]\nstep = "fit"\nmethod = "accel"\n')
    # a journal to recover: a short recording from the emulator, journal kept
    from calib_cli.acquire.emulator import Emulator
    from calib_cli.acquire.profile import load_imu_profile

    (d / "emu").mkdir()
    emu = Emulator(load_imu_profile("generic-bin6"), None, rate=1000,
                   link_dir=str(d / "emu")).start()
    try:
        assert _cli("record", "--imu", "generic-bin6", "--port", d / "emu" / "imu",
                    "--duration", "2", "--out", d / "jr.h5", "--keep-journal") == 0
    finally:
        emu.stop()
    return d


COMMANDS = [
    ("import", ["import", "csv", "IN/log.csv", "--plan", "IN/plan.toml", "--out", "FULL/raw.h5"]),
    ("simulate", ["simulate", "IN/plan.toml", "--out", "FULL/s.h5", "--seed", "1"]),
    ("fit", ["fit", "accel", "IN/raw.h5", "--out", "FULL/cal.h5"]),
    ("diagnose", ["diagnose", "IN/raw.h5", "--method", "accel", "--out", "FULL/d.h5"]),
    ("apply", ["apply", "IN/cal.h5", "IN/raw.h5", "--out", "FULL/c.h5"]),
    ("batch", ["batch", "IN/pipe.toml", "IN/arch", "--out", "FULL/bo"]),
    ("report", ["report", "IN/cal.h5", "--out", "FULL/rep"]),
    ("record", ["record", "--imu", "generic-bin6", "--port", "EMU/imu", "--duration", "1",
                "--out", "FULL/rr.h5"]),
]


# make test: three sizes; make validate K=full_disk: all five
FAST = ("0B", "20kB", "300kB")


@pytest.mark.parametrize("size", [s if s in FAST else pytest.param(
    s, marks=[pytest.mark.slow, pytest.mark.part("full_disk")]) for s in SIZES])
def test_full_disk(inputs, tmp_path, size):
    cmds = [(n, [a.replace("IN", str(inputs)).replace("EMU", str(tmp_path / "emu")) for a in args])
            for n, args in COMMANDS]
    jr = inputs / "jr.h5.journal"
    if jr.exists():
        cmds.append(("recover", ["recover", str(jr), "--out", "FULL/r.h5"]))
    env = dict(os.environ, PYTHONPATH=str(ROOT), MPLBACKEND="Agg")
    p = subprocess.run([sys.executable, "-c", _DRIVER, str(tmp_path), str(SIZES[size]),
                        json.dumps(cmds)], capture_output=True, text=True, env=env, timeout=900)
    if p.returncode != 0 and "mount" in p.stderr and "permission" in p.stderr.lower():
        pytest.skip("tmpfs cannot be mounted here")
    assert p.returncode == 0, f"the driver died (signal {-p.returncode})\n{p.stderr[-3000:]}"
    results = json.loads(p.stdout.strip().splitlines()[-1])
    bad = []
    for r in results:
        lines = [x for x in r["err"].splitlines() if x.strip()]
        files = {k: v for k, v in r["files"].items() if k != "filler"}
        if r["code"] == 0:
            ok = bool(files) and not any(Path(k).name.startswith(".") for k in files
                                         if Path(k).name != ".calib-batch.lock")
        else:
            kept = r["name"] == "record" and set(files) <= {"rr.h5.journal"} and \
                "journal" in r["err"]
            ok = (r["code"] == 2 and len(lines) == 1 and "calib: error:" in lines[0]
                  and "Traceback" not in r["err"] and (not files or kept))
            ok = ok and ("FULL" not in lines[0]) and (str(tmp_path) in lines[0])
        if not ok:
            bad.append((size, r["name"], r["code"], lines[:3], files))
    assert not bad, bad
    if SIZES[size] <= 4 << 10:  # nothing fits: every command said so
        assert all(r["code"] == 2 for r in results), [(r["name"], r["code"]) for r in results]
