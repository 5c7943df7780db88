"""Fuzz suite of issue 15: generated malformed inputs through the real command
line (click's test runner, in process; a sample through real subprocesses).

Every case is labelled by its generator: ``bad`` must end in exit 2, 3 or 4
with exactly one line on stderr that names the file, no traceback and no
output left behind; ``ok`` must exit 0; ``any`` (a random byte flip whose
effect the generator cannot know) may do either, but never exit 70 and never
more than one line. ``FUZZ_REPORT=1`` prints the counts per category.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import click
import numpy as np
import pytest
from click.testing import CliRunner

ROOT = Path(__file__).resolve().parents[1]
SEED = int(os.environ.get("FUZZ_SEED", "20261124"))

PLAN = """name = "small"
kind = "static"
sample_rate_hz = 50.0
transition_s = 1.0
[site]
latitude_deg = 50.0
height_m = 100.0
[unit]
serial = "SN-F"
""" + "".join(f"""[[segment]]
label = "{lab}"
attitude_deg = {att}
duration_s = 2.0
""" for lab, att in (("x-up", [0, -90, 0]), ("x-down", [0, 90, 0]), ("y-up", [90, 0, 0]),
                     ("y-down", [-90, 0, 0]), ("z-up", [0, 0, 0]), ("z-down", [180, 0, 0])))

PIPELINE = """name = "p"
[[step]]
step = "fit"
method = "accel"
"""


@click.command(context_settings={"ignore_unknown_options": True})
@click.argument("args", nargs=-1, type=click.UNPROCESSED)
def _entry(args):
    from calib_cli.cli.main import main

    main(list(args))


def run(*args):
    r = CliRunner().invoke(_entry, ["-q", *[str(a) for a in args]])
    return r.exit_code, r.stderr if hasattr(r, "stderr") else r.output


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    d = tmp_path_factory.mktemp("fuzzbase")
    (d / "plan.toml").write_text(PLAN)
    assert run("simulate", d / "plan.toml", "--out", d / "log.csv", "--seed", "3")[0] == 0
    assert run("import", "csv", d / "log.csv", "--plan", d / "plan.toml",
               "--out", d / "raw.h5")[0] == 0
    assert run("fit", "accel", d / "raw.h5", "--out", d / "cal.h5")[0] == 0
    (d / "pipe.toml").write_text(PIPELINE)
    return d


def _check(cat, label, expect, code, err, path, workdir, out_names, tally):
    lines = [ln for ln in err.splitlines() if ln.strip()]
    tally[cat] += 1
    tally[f"{cat} exit {code}"] += 1
    if os.environ.get("FUZZ_REPORT") == "2":
        print(cat, label, expect, code, err.strip()[:150])
    assert code != 70, (cat, label, err)
    assert "Traceback" not in err, (cat, label, err)
    assert "Warning" not in err, (cat, label, err)  # no numpy RuntimeWarning text
    if expect == "ok":
        assert code == 0, (cat, label, err)
        return
    if expect == "bad":
        assert code in (2, 3, 4), (cat, label, code, err)
    if code != 0:
        assert len(lines) == 1, (cat, label, err)
        assert Path(path).name in lines[0], (cat, label, err)
        for name in out_names:
            assert not (workdir / name).exists(), (cat, label, name)
        left = [p.name for p in workdir.iterdir() if p.name.startswith(".")]
        assert not left, (cat, label, left)


# ---------------------------------------------------------------------------
# generators: (label, expect, bytes or a function writing the file)


def csv_cases(text: str, rng):
    lines = text.splitlines()
    head = [i for i, ln in enumerate(lines) if not ln.startswith("#")][0]
    body = list(range(head + 1, len(lines)))
    out = [("empty", "bad", ""), ("only-comments", "bad", "# nothing\n"),
           ("no-time-column", "bad", "\n".join(
               [lines[head].replace("time,", "t,")] + lines[head + 1:]) + "\n"),
           ("header-only", "bad", "\n".join(lines[:head + 1]) + "\n"),
           ("binary", "bad", bytes(rng.integers(0, 256, 3000, dtype=np.uint8)).decode("latin-1")),
           ("valid", "ok", text)]
    for tok in ("abc", "nan", "inf", "-inf", "", "1e999", "0x1F", "1,2"):
        for _ in range(3):
            ls = list(lines)
            i = int(rng.choice(body))
            cells = ls[i].split(",")
            cells[int(rng.integers(0, 7))] = tok
            ls[i] = ",".join(cells)
            out.append((f"token-{tok or 'blank'}", "bad", "\n".join(ls) + "\n"))
    for _ in range(4):  # a row with a column missing or one too many
        ls = list(lines)
        i = int(rng.choice(body))
        ls[i] = ",".join(ls[i].split(",")[:-2]) if rng.random() < 0.5 else ls[i] + ",1.0"
        out.append(("ragged-row", "bad", "\n".join(ls) + "\n"))
    for _ in range(4):  # time going back
        ls = list(lines)
        i = int(rng.choice(body[10:-10]))
        ls[i], ls[i + 5] = ls[i + 5], ls[i]
        out.append(("time-back", "bad", "\n".join(ls) + "\n"))
    for v in ("1e20", "-5", "99", "2.5"):  # segment index outside the plan / not an integer
        ls = list(lines)
        i = int(rng.choice(body))
        cells = ls[i].split(",")
        cells[-1] = v
        ls[i] = ",".join(cells)
        out.append((f"segment-{v}", "bad", "\n".join(ls) + "\n"))
    for _ in range(8):  # cut anywhere
        n = int(rng.integers(1, len(text) - 1))
        out.append(("truncated", "any", text[:n]))
    for _ in range(6):  # random printable damage
        b = bytearray(text.encode())
        for _ in range(int(rng.integers(1, 20))):
            b[int(rng.integers(0, len(b)))] = int(rng.choice(list(b"xyz;:,.-e \t")))
        out.append(("printable-damage", "any", b.decode()))
    return out


def text_cases(text: str, rng):
    """`import text` inputs: whitespace logs without a header."""
    lines = [ln for ln in text.splitlines() if not ln.startswith("#")][1:]
    ws = "\n".join(" ".join(ln.split(",")) for ln in lines) + "\n"
    out = [("valid", "ok", ws), ("empty", "bad", ""), ("one-column", "bad", "1\n2\n3\n")]
    for tok in ("abc", "nan", "inf"):
        for _ in range(3):
            ls = ws.splitlines()
            i = int(rng.integers(0, len(ls)))
            cells = ls[i].split()
            cells[int(rng.integers(0, 7))] = tok
            ls[i] = " ".join(cells)
            out.append((f"token-{tok}", "bad", "\n".join(ls) + "\n"))
    for _ in range(4):
        ls = ws.splitlines()
        i = int(rng.integers(0, len(ls)))
        ls[i] = " ".join(ls[i].split()[:3])
        out.append(("short-row", "bad", "\n".join(ls) + "\n"))
    for _ in range(5):
        n = int(rng.integers(1, len(ws) - 1))
        out.append(("truncated", "any", ws[:n]))
    return out


def plan_cases(rng):
    seg = PLAN.index("[[segment]]")
    out = [("valid", "ok", PLAN),
           ("x_-key", "ok", PLAN + "x_atitude_deg = 3\n"),
           ("unknown-far-key", "ok", PLAN.replace("[site]", "operator = 'me'\n[site]")),
           ("not-toml", "bad", "kind = static\n"), ("empty", "bad", ""),
           ("no-segments", "bad", PLAN[:seg]),
           ("deep", "bad", "a = " + "[" * 3000 + "]" * 3000 + "\n"),
           ("kind-unknown", "bad", PLAN.replace('kind = "static"', 'kind = "rotary"')),
           ("kind-missing", "bad", PLAN.replace('kind = "static"\n', ""))]
    typos = {"attitude_deg": ["atitude_deg", "attitude_dge", "Attitude_deg", "attitud_deg"],
             "duration_s": ["durration_s", "duraton_s", "duration_S"],
             "label": ["lable", "labl"], "latitude_deg": ["latitud_deg", "lattitude_deg"],
             "sample_rate_hz": ["sample_rate_h", "sampel_rate_hz"],
             "transition_s": ["transiton_s"], "serial": ["serail"]}
    for key, bad in typos.items():
        for b in bad:
            out.append((f"typo-{b}", "bad", PLAN.replace(f"{key} =", f"{b} =", 1)))
    values = {"attitude_deg = [0, -90, 0]": ["attitude_deg = [0, -90]", "attitude_deg = 'up'",
                                             "attitude_deg = [true, false, true]",
                                             "attitude_deg = [nan, 0, 0]",
                                             "attitude_deg = [[0, 0, 0]]"],
              "duration_s = 2.0": ["duration_s = -1.0", "duration_s = 0", "duration_s = 1e12",
                                   "duration_s = 'long'", "duration_s = nan", "duration_s = inf"],
              "sample_rate_hz = 50.0": ["sample_rate_hz = 0", "sample_rate_hz = -5",
                                        "sample_rate_hz = 'fast'", "sample_rate_hz = nan"],
              "transition_s = 1.0": ["transition_s = -1", "transition_s = 'x'"],
              "latitude_deg = 50.0": ["latitude_deg = 91", "latitude_deg = 'N'",
                                      "latitude_deg = 50.0\ng = -9.8",
                                      "latitude_deg = 50.0\ng = 1e6",
                                      "latitude_deg = 50.0\ng = 0"],
              'label = "x-up"': ['label = ""', "label = 5",
                                 'label = "x-up"\nattitude_sigma_deg = -1',
                                 'label = "x-up"\nrepeat = "twice"',
                                 'label = "x-up"\nrotation_angle_deg = 90',
                                 'label = "x-up"\ntable_axis_enu = [0, 0, 0]']}
    for orig, news in values.items():
        for nv in news:
            out.append((f"value-{nv.splitlines()[-1][:24]}", "bad", PLAN.replace(orig, nv, 1)))
    for _ in range(8):
        n = int(rng.integers(1, len(PLAN) - 1))
        out.append(("truncated", "any", PLAN[:n]))
    return out


def pipeline_cases():
    out = [("valid", "ok", PIPELINE), ("empty", "bad", ""), ("not-toml", "bad", "[[step]\n"),
           ("options-int", "bad", PIPELINE + "options = 5\n"),
           ("options-list", "bad", PIPELINE + "options = [1]\n"),
           ("unknown-step", "bad", PIPELINE.replace('step = "fit"', 'step = "fitt"')),
           ("unknown-method", "bad", PIPELINE.replace('"accel"', '"accl"')),
           ("unknown-option", "bad", PIPELINE + 'options = { methd = "auto" }\n'),
           ("typo-top", "bad", "nmae = 'x'\n" + PIPELINE.split("\n", 1)[1]),
           ("typo-step-table", "bad", PIPELINE.replace("[[step]]", "[[stepp]]")),
           ("glob-outside", "bad", 'glob = "../*.h5"\n' + PIPELINE),
           ("glob-int", "bad", "glob = 5\n" + PIPELINE),
           ("output-bad", "bad", PIPELINE + 'output = "../x"\n'),
           ("no-steps", "bad", 'name = "p"\n'),
           ("deep", "bad", "a = " + "[" * 3000 + "]" * 3000 + "\n")]
    return out


def tolerance_cases():
    ok = "[param.accel_bias]\nmin_mg = -500\nmax_mg = 500\n"
    return [("valid", "ok", ok), ("empty", "bad", ""), ("not-toml", "bad", "[param.\n"),
            ("typo-param", "bad", ok.replace("accel_bias", "accel_biass")),
            ("typo-param-2", "bad", ok.replace("accel_bias", "acel_bias")),
            ("unknown-param", "bad", ok.replace("accel_bias", "banana")),
            ("typo-key", "bad", ok.replace("max_mg", "mx_mg")),
            ("unknown-top", "bad", "[params.accel_bias]\nmax = 1\n"),
            ("min-above-max", "bad", ok.replace("-500", "600")),
            ("wrong-shape", "bad", "[param.accel_K]\nmin = [1, 2]\n"),
            ("not-number", "bad", ok.replace("500\n", "'lots'\n", 1)),
            ("change-negative", "bad", ok + "max_change_sigma = -1\n"),
            ("param-not-table", "bad", "[param]\naccel_bias = 5\n")]


def imu_profile_cases():
    src = (ROOT / "profiles/imu/generic-bin6.toml").read_text()
    edits = [("rate_hz = 1000", "rate_hz = 'fast'"), ("rate_hz = 1000", "rate_hz = -1"),
             ("rate_hz = 1000", "rate_hzz = 1000"), ("bits = 16", "bits = 0"),
             ("bits = 16", "bits = 'x'"), ("baudrate = 921600", "baudrate = 'fast'"),
             ('parity = "N"', 'parity = "X"'), ("stopbits = 1", "stopbits = 7"),
             ('format = "binary"', 'format = "morse"'), ("scale = 1e-6", "scale = nan"),
             ("scale = 1e-6", "scale = 'big'"), ("scale = 1e-6", "scale = 0"),
             ('type = "i32"', 'type = "i33"'), ('unit = "deg/s"', 'unit = "furlong"'),
             ("[[field]]", "[[fields]]"), ("[transport]", "[transprt]")]
    out = []
    for a, b in edits:
        assert a in src, a
        out.append((f"{b[:20]}", "bad", src.replace(a, b, 1)))
    out += [("not-toml", "bad", "format = \n"), ("empty", "bad", "")]
    return out


def table_profile_cases():
    src = (ROOT / "profiles/turntable/generic-3axis.toml").read_text()
    edits = [("{roll_deg", "{rol_deg"), ("{roll_deg", "{speed"), ("[commands]", "[comands]"),
             ("timeout_s", "timeot_s"), ('kind = "serial"', 'kind = "robot"')]
    out = []
    for a, b in edits:
        if a in src:
            out.append((b[:20], "bad", src.replace(a, b, 1)))
    out += [("not-toml", "bad", "kind = \n")]
    return out


def h5_cases(base, rng):
    """(label, expect, writer(path)) for HDF5 files given where a recording is expected."""
    import h5py

    raw = (base / "raw.h5").read_bytes()
    cal = (base / "cal.h5").read_bytes()

    def copy_edit(fn, src=raw):
        def w(p):
            p.write_bytes(src)
            with h5py.File(p, "r+") as h5:
                fn(h5)
        return w

    def bytes_of(b):
        return lambda p: p.write_bytes(b)

    def rep(name, data):
        def f(h5):
            del h5[name]
            h5.create_dataset(name, data=data)
        return f

    out = [("valid", "ok", bytes_of(raw)), ("calibration-as-recording", "bad", bytes_of(cal)),
           ("empty", "bad", bytes_of(b"")), ("csv-as-h5", "bad", bytes_of(b"time,ax\n0,1\n")),
           ("future-version", "bad", copy_edit(lambda h: h.attrs.__setitem__("format_version", 7))),
           ("version-abc", "bad", copy_edit(lambda h: h.attrs.__setitem__("format_version", "abc"))),
           ("version-0", "bad", copy_edit(lambda h: h.attrs.__setitem__("format_version", 0))),
           ("no-kind", "bad", copy_edit(lambda h: h.attrs.__delitem__("kind"))),
           ("kind-allan", "bad", copy_edit(lambda h: h.attrs.__setitem__("kind", "allan")))]
    for name in ("samples", "samples/time", "samples/accel", "segments", "segments/start",
                 "segments/label", "site"):
        out.append((f"missing-{name}", "bad", copy_edit(lambda h, n=name: h.__delitem__(n))))
    with h5py.File(base / "raw.h5", "r") as h5:
        t, a = h5["samples/time"][()], h5["samples/accel"][()]
        start = h5["segments/start"][()]
    n = len(t)
    out += [("time-reversed", "bad", copy_edit(rep("samples/time", t[::-1]))),
            ("time-short", "bad", copy_edit(rep("samples/time", t[:-10]))),
            ("time-2d", "bad", copy_edit(rep("samples/time", t[:, None]))),
            ("time-strings", "bad", copy_edit(rep("samples/time", np.array([b"x"] * n)))),
            ("accel-1d", "bad", copy_edit(rep("samples/accel", a[:, 0]))),
            ("accel-short", "bad", copy_edit(rep("samples/accel", a[:-3]))),
            ("accel-empty", "bad", copy_edit(rep("samples/accel", np.zeros((0, 3))))),
            ("segments-ragged", "bad", copy_edit(rep("segments/start", start[:-1]))),
            ("segment-outside", "bad", copy_edit(rep("segments/start", start + 10 * n)))]
    for val in (np.nan, np.inf, -np.inf):
        for _ in range(2):
            b = a.copy()
            b[int(rng.integers(0, n)), int(rng.integers(0, 3))] = val
            out.append((f"accel-{val}", "bad", copy_edit(rep("samples/accel", b))))
        tt = t.copy()
        tt[int(rng.integers(0, n))] = val
        out.append((f"time-{val}", "bad", copy_edit(rep("samples/time", tt))))

    def huge(p):
        with h5py.File(base / "raw.h5", "r") as src, h5py.File(p, "w") as h5:
            for k, v in src.attrs.items():
                h5.attrs[k] = v
            s = h5.create_group("samples")
            s.create_dataset("time", shape=(10**11,), dtype="f8", chunks=(65536,))
            s.create_dataset("accel", shape=(10**11, 3), dtype="f8", chunks=(65536, 3))
            src.copy("segments", h5)
            src.copy("site", h5)

    out.append(("declares-1e11", "bad", huge))
    for _ in range(8):
        k = int(rng.integers(64, len(raw) - 1))
        out.append(("truncated", "bad", bytes_of(raw[:k])))
    with h5py.File(base / "raw.h5", "r") as h5:
        info = h5["samples/accel"].id.get_chunk_info(0)
        used = min(info.size, h5["samples/accel"].size * 8)  # the rows, not the chunk's padding
    for _ in range(6):  # flipped bytes inside the checksummed data
        b = bytearray(raw)
        o = info.byte_offset + int(rng.integers(0, max(used - 64, 1)))
        for i in range(o, o + int(rng.integers(1, 64))):
            b[i] ^= 0x5A  # (Fletcher-32 cannot tell a 0x0000 word from 0xFFFF: not 0xFF)
        out.append(("flipped-data", "bad", bytes_of(bytes(b))))
    for _ in range(8):  # flipped bytes anywhere: the generator cannot tell
        b = bytearray(raw)
        o = int(rng.integers(0, len(b) - 16))
        for i in range(o, o + int(rng.integers(1, 16))):
            b[i] ^= int(rng.integers(1, 256))
        out.append(("flipped-anywhere", "any", bytes_of(bytes(b))))
    return out


def cal_cases(base):
    """Calibrations given to apply/export: damaged parameters."""
    import h5py

    cal = (base / "cal.h5").read_bytes()

    def copy_edit(fn):
        def w(p):
            p.write_bytes(cal)
            with h5py.File(p, "r+") as h5:
                fn(h5)
        return w

    def setp(key, val):
        def f(h5):
            del h5[f"params/{key}"]
            h5[f"params/{key}"] = val
        return f

    return [("valid", "ok", lambda p: p.write_bytes(cal)),
            ("K-nan", "bad", copy_edit(setp("accel_K", np.full((3, 3), np.nan)))),
            ("b-inf", "bad", copy_edit(setp("accel_bias", np.array([np.inf, 0, 0])))),
            ("K-singular", "bad", copy_edit(setp("accel_K", np.zeros((3, 3))))),
            ("K-2x2", "bad", copy_edit(setp("accel_K", np.eye(2)))),
            ("b-len2", "bad", copy_edit(setp("accel_bias", np.zeros(2)))),
            ("params-empty", "bad", copy_edit(lambda h: [h["params"].__delitem__(k)
                                                          for k in list(h["params"])])),
            ("no-covariance", "bad", copy_edit(lambda h: h.__delitem__("covariance"))),
            ("recording-as-calibration", "bad",
             lambda p: p.write_bytes((base / "raw.h5").read_bytes())),
            ("future-version", "bad",
             copy_edit(lambda h: h.attrs.__setitem__("format_version", 9)))]


# ---------------------------------------------------------------------------


def test_fuzz_in_process(base, tmp_path):
    rng = np.random.default_rng(SEED)
    tally = Counter()
    seconds = Counter()
    plan = base / "plan.toml"
    n = 0

    def case(cat, label, expect, content, args_fn, outs=("o.h5",)):
        nonlocal n
        n += 1
        d = tmp_path / f"c{n}"
        d.mkdir()
        src = d / f"in-{cat}"
        if callable(content):
            content(src)
        elif isinstance(content, bytes):
            src.write_bytes(content)
        else:
            src.write_text(content, encoding="latin-1")
        t0 = time.perf_counter()
        code, err = run(*args_fn(src, d))
        seconds[cat] += time.perf_counter() - t0
        _check(cat, label, expect, code, err, src, d, outs, tally)

    text = (base / "log.csv").read_text()
    for label, expect, content in csv_cases(text, rng):
        case("csv", label, expect, content,
             lambda s, d: ["import", "csv", s, "--plan", plan, "--out", d / "o.h5"])
    for label, expect, content in text_cases(text, rng):
        case("text-log", label, expect, content,
             lambda s, d: ["import", "text", s, "--plan", plan, "--out", d / "o.h5",
                           "--columns", "time=1,ax=2,ay=3,az=4,gx=5,gy=6,gz=7,segment=8"])
    for label, expect, content in plan_cases(rng):
        case("plan", label, expect, content,
             lambda s, d: ["simulate", s, "--out", d / "o.h5", "--seed", "1"])
    # apply and show do not use the segments or the site: those mutants are fit's only
    structural = ("segments-ragged", "segment-outside", "missing-segments",
                  "missing-segments/start", "missing-segments/label", "missing-site")
    for label, expect, content in h5_cases(base, rng):
        case("hdf5-recording", label, expect, content,
             lambda s, d: ["fit", "accel", s, "--out", d / "o.h5"])
        if label not in structural:
            case("hdf5-recording", label, expect, content,
                 lambda s, d: ["apply", base / "cal.h5", s, "--out", d / "o.h5"])
        if label not in structural + ("calibration-as-recording",):
            case("hdf5-recording", label, expect, content, lambda s, d: ["show", s])
    for label, expect, content in cal_cases(base):
        if label not in ("no-covariance",):
            case("hdf5-calibration", label, expect, content,
                 lambda s, d: ["apply", s, base / "raw.h5", "--out", d / "o.h5"])
        case("hdf5-calibration", label, expect, content,
             lambda s, d: ["export", s, "--format", "json", "--out", d / "o.json"],
             outs=("o.json",))
    for label, expect, content in pipeline_cases():
        case("pipeline", label, expect, content,
             lambda s, d: ["batch", s, base / "raw.h5", "--out", d / "out"], outs=())
    for label, expect, content in tolerance_cases():
        case("tolerance", label, expect, content,
             lambda s, d: ["batch", base / "pipe.toml", base / "raw.h5", "--out", d / "out",
                           "--tolerances", s], outs=())
    for label, expect, content in imu_profile_cases():
        case("imu-profile", label, expect, content,
             lambda s, d: ["record", "--imu", str(s) + ".toml", "--port", d / "none",
                           "--duration", "1", "--out", d / "o.h5"])
    for label, expect, content in table_profile_cases():
        case("table-profile", label, expect, content,
             lambda s, d: ["record", "--imu", "generic-bin6", "--port", d / "none",
                           "--table", str(s) + ".toml", "--table-port", d / "none",
                           "--duration", "1", "--out", d / "o.h5"])
    if os.environ.get("FUZZ_REPORT"):
        print("\nfuzz cases per category:", dict(tally))
        print("seconds per category:", {k: round(v, 1) for k, v in seconds.items()})
    assert sum(v for k, v in tally.items() if " exit " not in k) >= 250


SUBPROCESS = [
    ("csv", "token-abc", lambda b, d: (d / "x.csv").write_text(
        (b / "log.csv").read_text().replace(",0\n", ",abc\n", 1)),
     lambda b, d: ["import", "csv", d / "x.csv", "--plan", b / "plan.toml", "--out", d / "o.h5"]),
    ("csv", "output-is-input", lambda b, d: (d / "x.csv").write_text((b / "log.csv").read_text()),
     lambda b, d: ["import", "csv", d / "x.csv", "--plan", b / "plan.toml", "--out", d / "x.csv"]),
    ("csv", "dev-zero", None,
     lambda b, d: ["import", "csv", "/dev/zero", "--plan", b / "plan.toml", "--out", d / "o.h5"]),
    ("csv", "directory", None,
     lambda b, d: ["import", "csv", d, "--plan", b / "plan.toml", "--out", d / "o.h5"]),
    ("plan", "typo", lambda b, d: (d / "p.toml").write_text(
        PLAN.replace("attitude_deg", "atitude_deg", 1)),
     lambda b, d: ["simulate", d / "p.toml", "--out", d / "o.h5"]),
    ("plan", "deep", lambda b, d: (d / "p.toml").write_text("a = " + "[" * 5000 + "]" * 5000),
     lambda b, d: ["simulate", d / "p.toml", "--out", d / "o.h5"]),
    ("plan", "rate-0", lambda b, d: (d / "p.toml").write_text(
        PLAN.replace("sample_rate_hz = 50.0", "sample_rate_hz = 0")),
     lambda b, d: ["simulate", d / "p.toml", "--out", d / "o.h5"]),
    ("plan", "duration-1e12", lambda b, d: (d / "p.toml").write_text(
        PLAN.replace("duration_s = 2.0", "duration_s = 1e12", 1)),
     lambda b, d: ["simulate", d / "p.toml", "--out", d / "o.h5"]),
    ("hdf5", "fit-to-proc", None, lambda b, d: ["fit", "accel", b / "raw.h5", "--out", "/proc/x.h5"]),
    ("hdf5", "fit-missing-dir", None,
     lambda b, d: ["fit", "accel", b / "raw.h5", "--out", d / "no" / "x.h5"]),
    ("hdf5", "fit-out-is-in", None, lambda b, d: ["fit", "accel", b / "raw.h5", "--out", b / "raw.h5"]),
    ("hdf5", "apply-out-is-in", None,
     lambda b, d: ["apply", b / "cal.h5", b / "raw.h5", "--out", b / "raw.h5"]),
    ("hdf5", "calibration-as-raw", None, lambda b, d: ["fit", "accel", b / "cal.h5", "--out", d / "o.h5"]),
    ("hdf5", "raw-as-calibration", None,
     lambda b, d: ["apply", b / "raw.h5", b / "raw.h5", "--out", d / "o.h5"]),
    ("hdf5", "csv-given-to-fit", None, lambda b, d: ["fit", "accel", b / "log.csv", "--out", d / "o.h5"]),
    ("hdf5", "truncated", lambda b, d: (d / "t.h5").write_bytes((b / "raw.h5").read_bytes()[:5000]),
     lambda b, d: ["fit", "accel", d / "t.h5", "--out", d / "o.h5"]),
    ("hdf5", "show-directory", None, lambda b, d: ["show", d]),
    ("pipeline", "options-int", lambda b, d: (d / "p.toml").write_text(PIPELINE + "options = 5\n"),
     lambda b, d: ["batch", d / "p.toml", b / "raw.h5", "--out", d / "out"]),
    ("tolerance", "typo", lambda b, d: (d / "t.toml").write_text("[param.accel_biass]\nmax = 1\n"),
     lambda b, d: ["batch", b / "pipe.toml", b / "raw.h5", "--out", d / "out", "--tolerances",
                   d / "t.toml"]),
    ("profile", "bits-0", lambda b, d: (d / "i.toml").write_text(
        (ROOT / "profiles/imu/generic-bin6.toml").read_text().replace("bits = 16", "bits = 0")),
     lambda b, d: ["record", "--imu", d / "i.toml", "--port", d / "none", "--duration", "1",
                   "--out", d / "o.h5"]),
    ("emulate", "corrupt-2", None,
     lambda b, d: ["emulate", "--imu", "generic-bin6", "--corrupt", "2", "--duration", "0.1"]),
]


# Cold starts of `python -m calib_cli` cost seconds each on a busy machine (SciPy
# imports); these few go through the real entry point from scratch, the others
# through real processes forked from one interpreter that imported calib once
# (their own pid, file descriptors, working directory and exit status).
COLD = {"token-abc", "fit-to-proc", "csv-given-to-fit", "options-int"}

FORK_SERVER = r"""
import json, os, sys
from calib_cli.cli.main import main
jobs = json.load(sys.stdin)
out = []
for args, err_path, cwd in jobs:
    pid = os.fork()
    if pid == 0:
        fd = os.open(err_path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        os.dup2(fd, 2)
        nul = os.open(os.devnull, os.O_RDWR)
        os.dup2(nul, 1)
        os.dup2(nul, 0)
        os.chdir(cwd)
        code = 70
        try:
            main(args)
        except SystemExit as e:
            code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(code)
    _, status = os.waitpid(pid, 0)
    out.append(os.waitstatus_to_exitcode(status))
print(json.dumps(out))
"""


def test_fuzz_subprocesses(base, tmp_path):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    codes = Counter()
    jobs = []
    for i, (cat, label, make, args) in enumerate(SUBPROCESS):
        d = tmp_path / f"s{i}"
        d.mkdir()
        if make:
            make(base, d)
        jobs.append((cat, label, d, sorted(p.name for p in d.iterdir()),
                     [str(a) for a in args(base, d)]))
    results = []  # (cat, label, d, before, returncode, stderr)
    cold = [j for j in jobs if j[1] in COLD]
    procs = [(j, subprocess.Popen([sys.executable, "-m", "calib_cli", *j[4]],
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                  env=env)) for j in cold]
    warm = [j for j in jobs if j[1] not in COLD]
    errs = [tmp_path / f"err{i}.txt" for i in range(len(warm))]
    server = subprocess.run(
        [sys.executable, "-c", FORK_SERVER], env=env, capture_output=True, text=True,
        input=json.dumps([(j[4], str(e), str(tmp_path)) for j, e in zip(warm, errs)]),
        timeout=300)
    assert server.returncode == 0, server.stderr
    for j, code, e in zip(warm, json.loads(server.stdout), errs, strict=True):
        results.append((*j[:4], code, e.read_text()))
    for j, p in procs:
        _, err = p.communicate(timeout=300)
        results.append((*j[:4], p.returncode, err))
    for cat, label, d, before, code, err in results:
        lines = [ln for ln in err.splitlines() if ln.strip()]
        codes[code] += 1
        assert code in (2, 3, 4), (cat, label, code, err)
        assert "Traceback" not in err and "Warning" not in err, (cat, label, err)
        assert len(lines) == 1, (cat, label, err)
        assert sorted(x.name for x in d.iterdir()) == before, (cat, label)
    if os.environ.get("FUZZ_REPORT"):
        print("\nsubprocess exit codes:", dict(codes), f"({len(cold)} cold starts, "
              f"{len(warm)} forked)")
    assert len(results) == len(SUBPROCESS) >= 20 and 70 not in codes
