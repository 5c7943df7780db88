"""Issue 37: never destroy what the user has, never crash, never pass a wrong
result. One test per numbered repro of the issue (points 10, 14 and 15 belong to
issues 36 and 33); each failed before the fix. Full disks: tests/test_full_disk.py;
the mutation fuzz: tests/test_fuzz37.py."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from calib_cli.io.h5 import read_calibration, write_calibration
from tests.hand_plans import rimu18_plan, six_position_plan

ROOT = Path(__file__).resolve().parents[1]

PLAN = six_position_plan("six", "SN-37")


def _cli(*args):
    from calib_cli.cli.main import main

    try:
        main(["-q", *[str(a) for a in args]])
    except SystemExit as exc:
        return exc.code if isinstance(exc.code, int) else 0
    return 0


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    d = tmp_path_factory.mktemp("r37")
    (d / "plan.toml").write_text(PLAN)
    assert _cli("simulate", d / "plan.toml", "--out", d / "log.csv", "--seed", "7") == 0
    assert _cli("import", "csv", d / "log.csv", "--plan", d / "plan.toml",
                "--out", d / "raw.h5") == 0
    assert _cli("fit", "accel", d / "raw.h5", "--out", d / "cal.h5") == 0
    return d


def _digest(path) -> str:
    import hashlib

    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def _edit(src, dst, fn):
    shutil.copy(src, dst)
    with h5py.File(dst, "r+") as f:
        fn(f)
    return dst


def _err_line(run_cli_result, path):
    code, _, err = run_cli_result
    lines = [x for x in err.splitlines() if x.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    assert str(Path(path).name) in lines[0], lines[0]
    return code, lines[0]


# -- 1. a directory output keeps what calib did not write ---------------------------


def test_1_report_into_a_directory_holding_the_input_keeps_everything(base, run_cli, tmp_path):
    r1 = tmp_path / "r1"
    (r1 / "sub").mkdir(parents=True)
    shutil.copy(base / "cal.h5", r1 / "cal.h5")
    (r1 / "notes.txt").write_text("mine")
    (r1 / "sub" / "x").write_text("x")
    before = _digest(r1 / "cal.h5")
    code, _, err = run_cli("-q", "report", r1 / "cal.h5", "--out", r1)
    assert code == 0, err
    assert _digest(r1 / "cal.h5") == before and (r1 / "notes.txt").read_text() == "mine"
    assert (r1 / "sub" / "x").exists() and (r1 / "report.html").exists()
    man = json.loads((r1 / "calib-manifest.json").read_text())
    assert "report.html" in man["files"] and "cal.h5" not in man["files"]
    # a file of another name calib would write: refused before anything is written
    (tmp_path / "r2").mkdir()
    (tmp_path / "r2" / "report.md").write_text("my own report")
    code, line = _err_line(run_cli("-q", "report", r1 / "cal.h5", "--out", tmp_path / "r2"),
                           "r2")
    assert code == 2 and "report.md" in line
    assert sorted(p.name for p in (tmp_path / "r2").iterdir()) == ["report.md"]


def test_1_diagnose_report_into_the_inputs_directory(base, run_cli, tmp_path):
    r3 = tmp_path / "r3"
    r3.mkdir()
    shutil.copy(base / "raw.h5", r3 / "raw.h5")
    before = _digest(r3 / "raw.h5")
    code, _, err = run_cli("-q", "diagnose", r3 / "raw.h5", "--method", "accel", "--out",
                           tmp_path / "d.h5", "--report", r3)
    assert code == 0, err
    assert _digest(r3 / "raw.h5") == before and (r3 / "summary.md").exists()


# -- 2, 3. outputs compared with inputs and with each other ---------------------------


def test_2_journal_equal_to_out_is_refused(run_cli, tmp_path):
    code, line = _err_line(run_cli("-q", "record", "--imu", "generic-bin6", "--port",
                                   tmp_path / "nope", "--duration", "3", "--out",
                                   tmp_path / "rr.h5", "--journal", tmp_path / "rr.h5"),
                           "rr.h5")
    assert code == 2 and "--journal and --out" in line
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("case", ["kalibr", "plot_same", "history_plot", "batch_log",
                                  "record_profile", "hard_link", "symlink"])
def test_3_outputs_that_overwrite_inputs(base, run_cli, tmp_path, case):
    raw = shutil.copy(base / "raw.h5", tmp_path / "raw.h5")
    if case == "kalibr":
        args, victim = ("allan", raw, "--kalibr", raw), raw
    elif case == "plot_same":
        args, victim = ("allan", raw, "--out", tmp_path / "X", "--plot", tmp_path / "X"), None
    elif case == "history_plot":
        (tmp_path / "h").mkdir()
        victim = shutil.copy(base / "cal.h5", tmp_path / "h" / "cal.h5")
        args = ("history", tmp_path / "h", "--unit", "", "--plot", victim)
    elif case == "batch_log":
        (tmp_path / "arch").mkdir()
        victim = shutil.copy(base / "raw.h5", tmp_path / "arch" / "r.h5")
        (tmp_path / "pipe.toml").write_text('name = "p"\n[[step]]\nstep = "fit"\n'
                                            'method = "accel"\n')
        args = ("batch", tmp_path / "pipe.toml", tmp_path / "arch", "--out", tmp_path / "bo",
                "--log", victim)
    elif case == "record_profile":
        victim = shutil.copy(ROOT / "profiles" / "imu" / "generic-bin6.toml", tmp_path / "p.toml")
        args = ("record", "--imu", victim, "--out", victim, "--force", "--port",
                tmp_path / "nope", "--duration", "1")
    elif case == "hard_link":
        os.link(raw, tmp_path / "hard.h5")
        args, victim = ("fit", "accel", raw, "--out", tmp_path / "hard.h5"), raw
    else:
        os.symlink(raw, tmp_path / "link.h5")
        args, victim = ("apply", base / "cal.h5", raw, "--out", tmp_path / "link.h5"), raw
    before = {p: _digest(p) for p in tmp_path.rglob("*") if p.is_file() and not p.is_symlink()}
    code, _, err = run_cli("-q", *args)
    assert code == 2, err
    assert len([x for x in err.splitlines() if x.strip()]) == 1, err
    after = {p: _digest(p) for p in tmp_path.rglob("*") if p.is_file() and not p.is_symlink()}
    assert after == before
    if victim is not None:
        assert str(Path(victim).name) in err


# -- 5 - 9. exit 70 --------------------------------------------------------------------


def _mutants(base, tmp_path):
    raw, cal = base / "raw.h5", base / "cal.h5"
    seg0 = None
    with h5py.File(raw) as f:
        seg0 = int(f["segments/start"][0])

    def cycle(f):
        del f["samples/accel"]
        f["samples/accel"] = h5py.SoftLink("/samples/accel")

    def badattr(name):
        def f(h):
            h.attrs[name] = np.bytes_(b"\xffSN")
        return f

    def setrow(ds, idx, val):
        def f(h):
            h[ds][idx] = val
        return f

    def replace(name, data):
        def f(h):
            del h[name]
            h[name] = data
        return f

    with h5py.File(raw) as f:
        acc = f["samples/accel"][()]
    out = {
        "cycle": (raw, cycle),
        "serial_not_utf8": (raw, badattr("unit_serial")),
        "command_not_utf8": (cal, badattr("command")),
        "created_not_utf8": (cal, badattr("created_utc")),
        "attitude_inf": (raw, setrow("segments/attitude", (0, 0), np.inf)),
        "attitude_partly_nan": (raw, setrow("segments/attitude", (0, 1), np.nan)),
        "accel_1e300": (raw, setrow("samples/accel", (seg0 + 3, 0), 1e300)),
        "accel_n2": (raw, replace("samples/accel", acc[:, :2])),
        "accel_n4": (raw, replace("samples/accel", np.hstack([acc, acc[:, :1]]))),
        "accel_int8": (raw, replace("samples/accel", acc.astype(np.int8))),
        "accel_text": (raw, replace("samples/accel", np.full(acc.shape, b"1.0"))),
        "accel_zero": (raw, replace("samples/accel", np.zeros_like(acc))),
        "accel_constant": (raw, replace("samples/accel", np.tile([1.0, 2.0, 3.0], (len(acc), 1)))),
        "accel_constant_g": (raw, replace("samples/accel", np.tile([0, 0, 9.81], (len(acc), 1)))),
        "g_inf": (raw, lambda h: h["site"].attrs.__setitem__("g", np.inf)),
        "g_negative": (raw, lambda h: h["site"].attrs.__setitem__("g", -9.81)),
    }
    return {k: (_edit(src, tmp_path / f"{k}.h5", fn)) for k, (src, fn) in out.items()}


def test_5_to_7_damaged_inputs_are_one_line_never_70(base, run_cli, tmp_path):
    files = _mutants(base, tmp_path)
    cmds = {"fit": lambda f: ("fit", "accel", f, "--out", tmp_path / "o.h5"),
            "show": lambda f: ("show", f),
            "diagnose": lambda f: ("diagnose", f, "--method", "accel", "--out", tmp_path / "o.h5"),
            "export": lambda f: ("export", f, "--format", "json", "--out", tmp_path / "o.json"),
            "apply": lambda f: ("apply", base / "cal.h5", f, "--out", tmp_path / "o.h5")}
    physics = ("accel_zero", "accel_constant", "accel_constant_g")  # the fits' to refuse
    for name, f in files.items():
        is_cal = name in ("command_not_utf8", "created_not_utf8")
        for c, args in cmds.items():
            if is_cal != (c == "export") and c != "show":
                continue
            if name in physics and c not in ("fit", "diagnose"):
                continue
            code, line = _err_line(run_cli("-q", *args(f)), f)
            assert code in (3, 4), (name, c, code, line)
            assert not (tmp_path / "o.h5").exists() and not (tmp_path / "o.json").exists()


def test_7_csv_cell_1e300_refused_at_import(base, run_cli, tmp_path):
    lines = (base / "log.csv").read_text().splitlines()
    i = next(k for k, x in enumerate(lines) if x and not x.startswith("#") and x[0].isdigit())
    cells = lines[i + 200].split(",")
    cells[1] = "1e300"
    lines[i + 200] = ",".join(cells)
    (tmp_path / "log.csv").write_text("\n".join(lines) + "\n")
    code, line = _err_line(run_cli("-q", "import", "csv", tmp_path / "log.csv", "--plan",
                                   base / "plan.toml", "--out", tmp_path / "raw.h5"), "log.csv")
    assert code == 3 and "1e+300" in line
    assert not (tmp_path / "raw.h5").exists()


def test_8_unknown_effect_and_string_temperature_range(base, run_cli, tmp_path):
    def tele(h):
        m = json.loads(h["model"].attrs["effects"])
        h["model"].attrs["effects"] = json.dumps(m + [{"name": "teleport"}])

    def trange(h):
        st = json.loads(h["stats"].attrs["json"])
        st["temp_range_degC"] = "20..30"
        h["stats"].attrs["json"] = json.dumps(st)

    for fn, word in ((tele, "teleport"), (trange, "temp_range_degC")):
        f = _edit(base / "cal.h5", tmp_path / "c.h5", fn)
        for args in (("apply", f, base / "raw.h5", "--out", tmp_path / "o.h5"),
                     ("export", f, "--format", "c-header", "--out", tmp_path / "o.h")):
            code, line = _err_line(run_cli("-q", *args), f)
            assert code == 3 and word in line


def test_9_nul_in_plan_strings(base, run_cli, tmp_path):
    for key, text in (("serial", PLAN.replace('serial = "SN-37"', 'serial = "SN\\u0000X"')),
                      ("label", PLAN.replace('label = "x-up"', 'label = "x\\u0000up"'))):
        (tmp_path / "p.toml").write_text(text)
        code, line = _err_line(run_cli("-q", "import", "csv", base / "log.csv", "--plan",
                                       tmp_path / "p.toml", "--out", tmp_path / "o.h5"), "p.toml")
        assert code == 3 and "NUL" in line, key
        assert not (tmp_path / "o.h5").exists()


@pytest.mark.parametrize("bad", ['attitude_deg = ["0", "-90", "0"]', "attitude_deg = [true, 0, 0]",
                                 "duration_s = true", 'duration_s = "3"', "duration_s = nan"])
def test_9_plan_values_typed(base, run_cli, tmp_path, bad):
    key = bad.split(" =")[0]
    text = PLAN.replace({"attitude_deg": "attitude_deg = [0, -90, 0]",
                         "duration_s": "duration_s = 3.0"}[key], bad, 1)
    (tmp_path / "p.toml").write_text(text)
    code, line = _err_line(run_cli("-q", "simulate", tmp_path / "p.toml", "--out",
                                   tmp_path / "o.h5"), "p.toml")
    assert code == 3 and key in line


# -- 11. diagnose rimu: more cycles than observable lever-arm entries --------------------


def test_11_rimu_diagnose_with_18_rotating_segments(run_cli, tmp_path):
    (tmp_path / "p.toml").write_text(rimu18_plan())
    assert run_cli("-q", "simulate", tmp_path / "p.toml", "--out", tmp_path / "r.h5",
                   "--seed", "2")[0] == 0
    code, _, err = run_cli("-q", "diagnose", tmp_path / "r.h5", "--method", "rimu", "--out",
                           tmp_path / "d.h5")
    assert code == 0, err


def test_11_lever_constraints_count_only_reached_rows():
    from calib_cli.methods.diagnose_fit import Fit

    labels = [("lever_arm", i) for i in range(54)]  # 18 cycles x 3
    unobs = np.ones(54, bool)
    unobs[[0, 1, 2, 30, 31, 32]] = False  # two rows the data reach
    f = Fit(None, None, {}, None, None, labels, None, np.zeros(1), None, unobs, {}, 0, 18)
    assert f.lever_constraints == 2 and f.n_free == 4


# -- 12, 13. silently wrong ------------------------------------------------------------


def test_12_negative_g_and_flipped_axis(base, run_cli, tmp_path):
    f = _edit(base / "raw.h5", tmp_path / "g.h5", lambda h: h["site"].attrs.__setitem__("g", -9.81))
    code, line = _err_line(run_cli("-q", "fit", "accel", f, "--out", tmp_path / "o.h5"), f)
    assert code == 3 and "g" in line

    def flip(h):
        h["samples/accel"][:, 2] *= -1

    f = _edit(base / "raw.h5", tmp_path / "z.h5", flip)
    code, line = _err_line(run_cli("-q", "fit", "accel", f, "--out", tmp_path / "o.h5"), f)
    assert code == 4 and "accel_K[2,2]" in line and "accel_axis_sign" in line
    # declared inverted by design: accepted, K[2,2] about -1
    with h5py.File(f, "r+") as h:
        t = h["plan"].attrs["text"]
        t = t.decode() if isinstance(t, bytes) else t
        h["plan"].attrs["text"] = t.replace('serial = "SN-37"',
                                            'serial = "SN-37"\naccel_axis_sign = [1, 1, -1]')
    code, _, err = run_cli("-q", "fit", "accel", f, "--out", tmp_path / "o.h5")
    assert code == 0, err
    assert read_calibration(tmp_path / "o.h5").params["accel_K"][2, 2] < -0.9


def test_13_calibration_without_K_is_refused(base, run_cli, tmp_path):
    f = _edit(base / "cal.h5", tmp_path / "c.h5", lambda h: h["params"].__delitem__("accel_K"))
    for args in (("apply", f, base / "raw.h5", "--out", tmp_path / "o.h5"),
                 ("export", f, "--format", "c-header", "--out", tmp_path / "o.h"),
                 ("show", f)):
        code, line = _err_line(run_cli("-q", *args), f)
        assert code == 3 and "accel_K" in line
    assert not list(p for p in tmp_path.iterdir() if p.name != "c.h5")


# -- 16. checksums on every dataset -----------------------------------------------------


def _datasets(h) -> list:
    out = []
    h.visititems(lambda n, o: out.append(o) if isinstance(o, h5py.Dataset) else None)
    return out


def test_16_every_dataset_checksummed_and_text_fixed_length(base):
    for f in (base / "raw.h5", base / "cal.h5"):
        with h5py.File(f) as h:
            dsets = _datasets(h)
            for ds in dsets:
                if ds.size >= 1 and ds.shape:
                    assert ds.fletcher32, ds.name
                assert h5py.check_vlen_dtype(ds.dtype) is None, ds.name
        # superblock version 2 or 3 (format 1.8+): checksummed superblock and headers
        assert Path(f).read_bytes()[8] >= 2


def test_16_flipped_covariance_or_segment_byte_is_refused(base, run_cli, tmp_path):
    for src, name in ((base / "cal.h5", "covariance/matrix"), (base / "raw.h5", "segments/start"),
                      (base / "cal.h5", "tables/g_table")):
        with h5py.File(src) as h:
            if name not in h:
                continue
            off = h[name].id.get_offset() if h[name].chunks is None else \
                h[name].id.get_chunk_info(0).byte_offset
        data = bytearray(src.read_bytes())
        data[off + 3] ^= 0x10
        f = tmp_path / src.name
        f.write_bytes(bytes(data))
        cmd = ("show", f, "--covariance") if "cal" in src.name else ("show", f)
        code, line = _err_line(run_cli("-q", *cmd), f)
        assert code == 3 and ("damaged" in line or "checksum" in line), line


# -- 17. C headers compile for every kind -------------------------------------------------


def _gcc(header: Path, n_accel=3) -> None:
    src = header.parent / "use.c"
    src.write_text(f'#include "{header.name}"\nint calib_use(void) {{ return 0; }}\n')
    subprocess.run(["gcc", "-std=c99", "-Wall", "-Wextra", "-Werror", "-c", str(src), "-o",
                    str(header.parent / "use.o")], check=True, cwd=header.parent,
                   capture_output=True)


def _cal_kinds(tmp_path):
    from samples_9 import triad_calibration

    out = {}
    c = triad_calibration()
    write_calibration(tmp_path / "triad.h5", c)
    out["triad"] = tmp_path / "triad.h5"
    tiny = dict(c.params, accel_bias=np.array([1e-300, -1e-41, 0.02]))
    write_calibration(tmp_path / "tiny.h5", type(c)(**{**c.__dict__, "params": tiny}))
    out["tiny"] = tmp_path / "tiny.h5"
    out["rimu"] = ROOT / "tests" / "fixtures" / "v0.1.0" / "cal_rimu.h5"
    # thermal, without temp_range_degC (its bounds were written as 1e300 for float)
    from calib_cli.model.effects import make_effect
    from calib_cli.model.truth import describe_effect

    th = make_effect("temperature_drift", "accel", order=1)
    model = [d for d in c.model if d.get("sensor") == "accel"] + [describe_effect(th)]
    params = {k: v for k, v in c.params.items() if k.startswith("accel")}
    params.update(accel_temp_bias=np.array([1e-4, -2e-4, 3e-5]),
                  accel_temp_scale=np.array([1e-5, 2e-6, -3e-6]))
    thermal = type(c)(**{**c.__dict__, "params": params, "model": model, "stats": {},
                         "sigma": {k: np.full(np.shape(v), 1e-6) for k, v in params.items()}})
    write_calibration(tmp_path / "thermal.h5", thermal)
    out["thermal"] = tmp_path / "thermal.h5"
    return out


@pytest.mark.skipif(shutil.which("gcc") is None, reason="no gcc")
@pytest.mark.parametrize("single", [False, True])
def test_17_c_header_compiles_for_every_kind(run_cli, tmp_path, single):
    sys.path.insert(0, str(ROOT / "tests"))
    for kind, f in _cal_kinds(tmp_path).items():
        h = tmp_path / f"{kind}.h"
        code, _, err = run_cli("-q", "export", f, "--format", "c-header", "--out", h,
                               *(["--float"] if single else []))
        assert code == 0, (kind, err)
        _gcc(h)


def test_17_float_beyond_range_is_refused():
    from calib_cli.errors import OutputError
    from calib_cli.io.export import _c_lit

    assert _c_lit(1e-300, True) == "0.0f" and _c_lit(-1e-41, True).endswith("f")
    assert float(_c_lit(1e-300, False)) == 1e-300
    with pytest.raises(OutputError, match="beyond what a float holds"):
        _c_lit(1e39, True, "CALIB_X[0]")
    assert float(_c_lit(1e39, False)) == 1e39


# -- 18. messages name the file and the object ------------------------------------------


def test_18_damaged_string_heap_names_file_and_object(base, run_cli, tmp_path):
    """A calibration written with variable-length strings (as calib < 0.2 did): a
    damaged heap is one line naming the file, not `calib: error: OSError`."""
    f = tmp_path / "old.h5"
    with h5py.File(f, "w") as h:
        h.attrs["kind"] = "calibration"
        h.attrs["format_version"] = 1
        g = h.create_group("segments")
        g.create_dataset("label", data=["a" * 40] * 3, dtype=h5py.string_dtype())
    data = bytearray(f.read_bytes())
    i = data.find(b"a" * 40)
    data[i - 16:i + 40] = bytes(56)  # the heap object's header and text
    f.write_bytes(bytes(data))
    code, line = _err_line(run_cli("-q", "show", f), f)
    assert code == 3 and "OSError" not in line
