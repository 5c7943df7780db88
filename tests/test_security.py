"""Trust boundaries (issue 16, docs/security.md): text from a file never
becomes code, markup or a YAML structure; HDF5 inputs cannot reach other
files or declare more data than they hold; the documented Dask recipe
listens on loopback only."""

from __future__ import annotations

import contextlib
import csv
import io
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import h5py
import numpy as np
import pytest

from calib_cli.cli.main import main
from calib_cli.io import escape
from calib_cli.io.export import (
    c_header_symbols,
    export_object,
    to_c_header,
    to_csv,
    to_json,
    to_yaml,
)
from calib_cli.io.h5 import write_calibration, write_raw
from calib_cli.io.plan import parse_plan
from calib_cli.sim.simulate import simulate

try:  # tests/ as rootdir-inserted path (no __init__.py) or as a package
    from samples_9 import PLAN, triad_calibration
except ImportError:  # pragma: no cover
    from tests.samples_9 import PLAN, triad_calibration

ROOT = Path(__file__).resolve().parents[1]
GCC = shutil.which("gcc") or shutil.which("cc")
NM = shutil.which("nm")

# what an attacker puts into every free-text field of a file
HOSTILE = [
    "SN-1 */ int calib_injected(void) { return 1337; } /*",
    "line\nbreak\r\n#include <stdlib.h>\n#define CALIB_ACCEL_BIAS evil",
    "back\\slash at the end\\",
    "<script>alert('x')</script><img src=x onerror=alert(1)>",
    "&anchor *anchor !!python/object/apply:os.system ['id'] {a: b} [c] # not a comment",
    "quotes \" ' ` and %s %n {{}}",
    "??/ trigraph ??= ??( ??' // and /* nested",
    "- [link](javascript:alert(1)) ![img](http://evil/x.png) | cell | *em* _u_",
    "yes",
    "1e-05",
    "unicode \u00e9 \u2713 \u2028 \u0085 \U0001f600 \x7f \x1b[31mred",
    r"mathtext $\undefinedcommand{x}$ and $x^{$",  # crashed matplotlib (ValueError)
]
NUL = "nul\x00byte"  # only at the library level: HDF5 strings cannot hold NUL


def run_cli(*args) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            main([str(a) for a in args])
            code = 0
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else 0
    return code, out.getvalue(), err.getvalue()


# ---------------------------------------------------------------------------
# the escapers themselves


@pytest.mark.parametrize("text", HOSTILE + [NUL, ""])
def test_escapers_round_trip(text):
    import yaml

    assert yaml.safe_load("k: " + escape.yaml_string(text)) == {"k": text}
    assert yaml.safe_load(escape.yaml_key(text) + ": 1") == {text: 1}
    assert json.loads(escape.json_text({text: text})) == {text: text}
    row = list(csv.reader(io.StringIO(escape.csv_text([[escape.csv_cell(text), "1"]]))))
    assert len(row) == 1 and row[0][1] == "1"
    lit = escape.c_string(text)
    assert "\n" not in lit and "*/" not in lit and "??" not in lit
    md = escape.md_text(text)
    assert "<" not in md and "\n" not in md and "](" not in md.replace("\\](", "")
    assert "<" not in escape.html_text(text)


def test_yaml_numbers_are_floats_in_yaml_1_1():
    import yaml

    for x in (1e-05, 1e20, -2.5e-300, 0.1, 3.0, 1 / 3):
        assert yaml.safe_load(escape.yaml_number(x)) == x
        assert json.loads(escape.yaml_number(x)) == x


# ---------------------------------------------------------------------------
# exports: hostile text in every free-text field


def _hostile_cal(text: str):
    """A calibration whose every free-text field holds ``text``."""
    c = triad_calibration()
    key = "x" + text.replace("/", "|")  # a parameter name (HDF5 names hold no '/')
    return replace(c, method=text, serial=text, units={**c.units, "accel_bias": text, key: text},
                   params={**c.params, key: np.zeros(2)}, sigma={**c.sigma, key: np.ones(2)},
                   raw_units={"accel": text, "gyro": text}), key


def _prov(text: str) -> dict:
    return {"sha256": text, "created_utc": text, "command": f"calib fit accel {text}",
            "tool_version": text}


C_VOCABULARY = {"typedef", "static", "const", "char", "double", "float", "inline", "void",
                "for", "int", "A", "W", "f", "w", "u", "i"}


def _c_strip_strings(text: str) -> str:
    return re.sub(r'"(\\.|[^"\\\n])*"', '""', text)


def _check_c_header(d: Path, text: str, prefix: str, expect: dict, gyro: bool = True) -> None:
    """The header compiles with -Wall -Werror, defines exactly the documented
    names (nm, -dM, and the identifiers left after the preprocessor), and its
    string constants hold exactly the expected bytes."""
    syms = c_header_symbols(prefix, accel=True, gyro=gyro)
    documented = set(syms["objects"]) | set(syms["functions"])
    h = d / "evil.h"
    h.write_text(text, encoding="utf-8")
    # 1. the objects and functions it defines: keep every static one, list with nm
    use = d / "use.c"
    use.write_text('#include "evil.h"\n', encoding="utf-8")
    for std in ("-std=c99", "-std=gnu11"):  # c99: trigraphs on
        subprocess.run([GCC, std, "-Wall", "-Wextra", "-Werror", "-O0", "-fkeep-static-functions",
                        "-fkeep-inline-functions", "-c", "use.c", "-o", "use.o"], cwd=d,
                       check=True, capture_output=True)
        if NM:
            out = subprocess.run([NM, "use.o"], cwd=d, check=True, capture_output=True,
                                 text=True).stdout
            names = {ln.split()[-1] for ln in out.splitlines() if len(ln.split()) == 3}
            assert names == documented, names ^ documented
    # 2. the macros it defines
    def macros(src):
        out = subprocess.run([GCC, "-std=c99", "-dM", "-E", "-x", "c", src], cwd=d, check=True,
                             capture_output=True, text=True).stdout
        return {ln.split()[1].split("(")[0] for ln in out.splitlines()}
    (d / "empty.h").write_text("")
    assert macros("evil.h") - macros("empty.h") == set(syms["macros"])
    # 3. every identifier of the preprocessed header, string constants aside
    pre = subprocess.run([GCC, "-std=c99", "-E", "-P", "-x", "c", "evil.h"], cwd=d, check=True,
                         capture_output=True, text=True).stdout
    idents = set(re.findall(r"(?<![\w.])[A-Za-z_]\w*", _c_strip_strings(pre)))
    assert idents <= C_VOCABULARY | documented | set(syms["types"]), \
        idents - C_VOCABULARY - documented
    assert "calib_injected" not in idents and "return" not in idents
    # 4. the string constants hold the file's text, byte for byte
    strs = [n for n in syms["objects"] if n.split("_", 1)[1] in
            ("SOURCE_FILE", "SOURCE_SHA256", "SOURCE_CREATED_UTC", "SOURCE_COMMAND",
             "SOURCE_TOOL_VERSION", "METHOD", "UNIT_SERIAL", "ACCEL_UNITS", "GYRO_UNITS")]
    prog = ['#include <stdio.h>', '#include "evil.h"', "int main(void)", "{",
            "    double A[3] = {0.1, 0.2, 9.8}, W[3] = {0.01, 0, 0}, f[3], w[3];",
            f"    {prefix}_correct_accel(A, f);",
            f"    {prefix}_correct_gyro(W, f, w);" if gyro else "    (void)W; (void)w;"]
    for n in strs:
        prog.append(f'    printf("{n} %zu\\n", sizeof {n} - 1); '
                    f"fwrite({n}, 1, sizeof {n} - 1, stdout); putchar('\\n');")
    prog += ["    return f[0] != f[0];", "}"]
    (d / "prog.c").write_text("\n".join(prog) + "\n", encoding="utf-8")
    subprocess.run([GCC, "-std=c99", "-Wall", "-Werror", "-o", "prog", "prog.c"], cwd=d,
                   check=True, capture_output=True)
    raw = subprocess.run([str(d / "prog")], check=True, capture_output=True).stdout
    got, pos = {}, 0
    while pos < len(raw):
        eol = raw.index(b"\n", pos)
        name, n = raw[pos:eol].decode().split()
        got[name] = raw[eol + 1:eol + 1 + int(n)]
        pos = eol + 2 + int(n)
    for suffix, value in expect.items():
        assert got[f"{prefix.upper()}_{suffix}"] == value.encode("utf-8"), suffix


@pytest.mark.skipif(GCC is None, reason="no C compiler")
@pytest.mark.parametrize("text", HOSTILE[:8] + [NUL] + HOSTILE[10:])
def test_c_header_hostile_fields(tmp_path, text):
    cal, _ = _hostile_cal(text)
    src = "cal " + text.replace("/", "|") + ".h5"
    hdr = to_c_header(cal, _prov(text), src, prefix="imu7")
    _check_c_header(tmp_path, hdr, "imu7",
                    {"SOURCE_FILE": src, "SOURCE_SHA256": text, "SOURCE_CREATED_UTC": text,
                     "SOURCE_COMMAND": f"calib fit accel {text}", "SOURCE_TOOL_VERSION": text,
                     "METHOD": text, "UNIT_SERIAL": text, "ACCEL_UNITS": text,
                     "GYRO_UNITS": text})


@pytest.mark.parametrize("text", HOSTILE + [NUL])
def test_json_yaml_csv_hostile_fields(text):
    import yaml

    cal, key = _hostile_cal(text)
    src = "cal " + text + ".h5"
    obj = export_object(cal, _prov(text), src)
    j, y = json.loads(to_json(obj)), yaml.safe_load(to_yaml(obj))
    assert j == y  # one object, whichever reader
    for o in (j, y):
        assert o["unit"]["serial"] == o["method"] == o["source"]["sha256"] == text
        assert o["source"]["command"] == f"calib fit accel {text}"
        assert o["source"]["file"] == src
        assert o["raw_units"] == {"accel": text, "gyro": text}
        assert o["units"][key] == o["units"]["accel_bias"] == text
        assert o["params"][key] == [0.0, 0.0]
        np.testing.assert_array_equal(o["correction"]["accel"]["K"], obj["correction"]["accel"]["K"])
    assert to_json(obj).isascii() and to_yaml(obj).isascii()
    rows = list(csv.reader(io.StringIO(to_csv(cal, obj))))
    assert all(len(r) == 5 for r in rows)
    assert [r[0] for r in rows if r[4] == escape.csv_cell(text) and r[0] == escape.csv_cell(key)]


# the same through the command line: hostile plan -> simulate -> fit -> export/report

HOSTILE_PLAN = """
name = {name}
kind = "static"
sample_rate_hz = 50.0
notes = {name}
[site]
latitude_deg = 50.45
[unit]
serial = {serial}
""" + "".join(f"""
[[segment]]
label = {{lab{i}}}
attitude_deg = {att}
duration_s = 4
""" for i, att in enumerate([[0, 0, 0], [180, 0, 0], [0, -90, 0], [0, 90, 0], [90, 0, 0],
                             [-90, 0, 0]]))


def _toml_str(s: str) -> str:
    """A TOML basic string holding ``s``."""
    out = []
    for c in s:
        if c in '"\\':
            out.append("\\" + c)
        elif ord(c) < 0x20 or ord(c) == 0x7F:
            out.append("\\u%04x" % ord(c))
        else:
            out.append(c)
    return '"' + "".join(out) + '"'


@pytest.fixture(scope="module")
def hostile_files(tmp_path_factory):
    d = tmp_path_factory.mktemp("hostile")
    serial = HOSTILE[0] + " " + HOSTILE[3]
    label_texts = [HOSTILE[k] + f" #{i}" for i, k in enumerate((1, 3, 5, 7, 10, 11))]
    labels = {f"lab{i}": _toml_str(t) for i, t in enumerate(label_texts)}
    plan = d / "plan.toml"
    plan.write_text(HOSTILE_PLAN.format(name=_toml_str(HOSTILE[4]), serial=_toml_str(serial),
                                        **labels), encoding="utf-8")
    raw = d / "raw.h5"
    code, _, err = run_cli("simulate", plan, "--out", raw, "--seed", "1")
    assert code == 0, err
    # the command line, the output's name: hostile too (the name lands in the header)
    cal = d / ("cal " + HOSTILE[1] + " ??= \\ <b> *.h5")
    code, _, err = run_cli("fit", "accel", raw, "--out", cal, "--method", "vector")
    assert code == 0, err
    # what a crafted file adds: method, command, creation time, units (HDF5 attributes)
    crafted = d / "crafted.h5"
    shutil.copy(cal, crafted)
    with h5py.File(crafted, "a") as h5:
        h5.attrs["command"] = HOSTILE[2] + HOSTILE[5]
        h5.attrs["created_utc"] = HOSTILE[6]
        h5.attrs["tool_version"] = HOSTILE[7]
        h5.attrs["method"] = HOSTILE[0]
        h5.attrs["raw_units"] = json.dumps({"accel": HOSTILE[3], "gyro": HOSTILE[4]})
        h5["units"].attrs["accel_bias"] = HOSTILE[10]
    return {"dir": d, "raw": raw, "cal": cal, "crafted": crafted, "serial": serial,
            "labels": label_texts}


@pytest.mark.skipif(GCC is None, reason="no C compiler")
def test_cli_c_header_from_hostile_plan(hostile_files, tmp_path):
    f = hostile_files
    for which in ("cal", "crafted"):
        out = tmp_path / f"{which}.h"
        code, _, err = run_cli("export", f[which], "--format", "c-header", "--out", out,
                               "--prefix", "calib")
        assert code == 0, err
        text = out.read_text(encoding="utf-8")
        assert "calib_injected" not in _c_strip_strings(text)
        with h5py.File(f[which]) as h5:
            method = h5.attrs["method"]
            command = h5.attrs["command"]
        expect = {"UNIT_SERIAL": f["serial"], "SOURCE_FILE": Path(f[which]).name,
                  "METHOD": method.decode() if isinstance(method, bytes) else method,
                  "SOURCE_COMMAND": command.decode() if isinstance(command, bytes) else command}
        if which == "crafted":
            expect.update({"SOURCE_CREATED_UTC": HOSTILE[6], "SOURCE_TOOL_VERSION": HOSTILE[7],
                           "ACCEL_UNITS": HOSTILE[3]})  # an accelerometer calibration
        d = tmp_path / which
        d.mkdir()
        _check_c_header(d, text, "calib", expect, gyro=False)
        # the reproducer: a program calling the injected function no longer builds
        (d / "attack.c").write_text('#include <stdio.h>\n#include "evil.h"\n'
                                    'int main(void) { printf("%d\\n", calib_injected()); '
                                    "return 0; }\n")
        r = subprocess.run([GCC, "-std=c99", "-Wall", "-o", "attack", "attack.c"], cwd=d,
                           capture_output=True, text=True)
        assert r.returncode != 0 and "calib_injected" in r.stderr


def test_cli_json_yaml_from_hostile_plan(hostile_files):
    import yaml

    f = hostile_files
    code, js, err = run_cli("export", f["crafted"], "--format", "json")
    assert code == 0, err
    code, ys, err = run_cli("export", f["crafted"], "--format", "yaml")
    assert code == 0, err
    j, y = json.loads(js), yaml.safe_load(ys)
    assert j == y
    assert j["unit"]["serial"] == f["serial"] and j["method"] == HOSTILE[0]
    assert j["source"]["command"] == HOSTILE[2] + HOSTILE[5]
    assert j["raw_units"] == {"accel": HOSTILE[3], "gyro": HOSTILE[4]}
    assert j["units"]["accel_bias"] == HOSTILE[10]
    # show --json is the same serialiser
    code, so, err = run_cli("show", f["crafted"], "--json")
    assert code == 0, err
    assert json.loads(so)["unit"]["serial"] == f["serial"]


def test_terminal_shows_file_text_inert(hostile_files, tmp_path):
    """calib show: rich markup in a file ([/], [link=...]) is shown, not
    interpreted (it used to crash with exit 70); no escape sequence reaches
    the terminal."""
    crafted = tmp_path / "term.h5"
    shutil.copy(hostile_files["crafted"], crafted)
    with h5py.File(crafted, "a") as h5:
        h5.attrs["unit_serial"] = "[link=file:///etc/passwd]click[/link] [/] \x1b]0;owned\x07"
        h5.attrs["method"] = "[bold red]x[/] \x1b[2J"
    for f in (crafted, hostile_files["raw"]):
        code, out, err = run_cli("show", f)
        assert code == 0, err
        assert "\x1b" not in out and "\x07" not in out
    code, out, _ = run_cli("show", crafted)
    assert "[link=file:///etc/passwd]click[/link]" in out and "[/]" in out


def _md_tokens(md: str):
    from markdown_it import MarkdownIt

    parser = MarkdownIt("commonmark").enable("table")  # raw HTML enabled, as renderers do
    stack = list(parser.parse(md))
    while stack:
        t = stack.pop()
        yield t
        stack.extend(t.children or [])


def _check_markdown(md: str, figures=()):
    assert "<" not in md, md[max(0, md.find("<") - 80):md.find("<") + 80]
    for t in _md_tokens(md):
        assert t.type not in ("html_block", "html_inline"), t
        assert t.type != "link_open", t  # no link in a report
        if t.type == "image":
            assert t.attrs["src"] in figures, t.attrs
    from markdown_it import MarkdownIt

    html = MarkdownIt("commonmark").enable("table").render(md)
    assert "<script" not in html.lower() and "<img src=x" not in html.lower()


def test_markdown_report_has_no_raw_html(hostile_files, tmp_path):
    f = hostile_files
    for which in ("cal", "crafted"):
        out = tmp_path / which
        code, _, err = run_cli("report", f[which], f["raw"], "--out", out)
        assert code == 0, err
        md = (out / "report.md").read_text(encoding="utf-8")
        figures = {p.name for p in out.glob("*.png")}
        _check_markdown(md, figures)
        page = (out / "report.html").read_text(encoding="utf-8")
        assert "<script" not in page.lower() and "<img src=x" not in page
        assert "&lt;script&gt;" in page  # shown as text, escaped
    # the serial is still there, readable: the renderer shows it as text
    from markdown_it import MarkdownIt

    html = MarkdownIt("commonmark").enable("table").render(md)
    assert "&lt;script&gt;alert(" in html and "calib_injected(void)" in html


def test_markdown_escaper_every_hostile_string():
    from calib_cli.report.builder import Section, Table, write_report

    for i, text in enumerate(HOSTILE + [NUL]):
        secs = [Section(text, text=[text, f"note: {text}"],
                        tables=[Table(text, [text, "b"], [[text, text]])])]
        import tempfile

        with tempfile.TemporaryDirectory() as d:
            write_report(secs, text, d)
            md = Path(d, "report.md").read_text(encoding="utf-8")
            _check_markdown(md)
            # every table row keeps its two cells
            rows = [ln for ln in md.splitlines() if ln.startswith("| ")]
            assert all(ln.count(" | ") == 1 for ln in rows), (i, rows)


# ---------------------------------------------------------------------------
# --prefix


@pytest.mark.parametrize("prefix", ["1abc", "a b", "a*/", "int", "_x", "x" * 33, "a-b", "é"])
def test_prefix_must_be_a_c_identifier(prefix, tmp_path):
    cal = tmp_path / "cal.h5"
    write_calibration(cal, triad_calibration())
    code, out, err = run_cli("export", cal, "--format", "c-header", "--prefix", prefix,
                             "--out", tmp_path / "x.h")
    assert code == 2 and out == ""
    assert len(err.strip().splitlines()) == 1 and "--prefix" in err and "C identifier" in err
    assert not (tmp_path / "x.h").exists()


# ---------------------------------------------------------------------------
# HDF5: links, virtual datasets, references, declared size


@pytest.fixture(scope="module")
def h5_files(tmp_path_factory):
    d = tmp_path_factory.mktemp("h5links")
    raw, cal = d / "raw.h5", d / "cal.h5"
    write_raw(raw, simulate(parse_plan(PLAN), None, seed=3))
    write_calibration(cal, triad_calibration())
    with h5py.File(raw) as src, h5py.File(d / "other.h5", "w") as o:  # the linked file
        o["accel"] = src["samples/accel"][()]
        o["gyro"] = src["samples/gyro"][()]
        o["bias"] = np.zeros(3)
        o["K"] = np.eye(3)
    out = {"dir": d, "raw": raw, "cal": cal}
    for base, path in (("raw", raw), ("cal", cal)):
        for kind in ("external", "virtual", "reference", "reference-attr", "huge"):
            p = d / f"{base}-{kind}.h5"
            shutil.copy(path, p)
            with h5py.File(p, "a") as h5:
                if base == "raw":
                    grp, name, src, shape = h5["samples"], "accel", "accel", h5["samples/accel"].shape
                else:
                    grp, name, src, shape = h5["params"], "accel_K", "K", (3, 3)
                if kind == "external":
                    del grp[name]
                    grp[name] = h5py.ExternalLink("other.h5", "/" + src)
                elif kind == "virtual":
                    del grp[name]
                    lay = h5py.VirtualLayout(shape=shape, dtype="f8")
                    lay[...] = h5py.VirtualSource("other.h5", src, shape=shape)
                    grp.create_virtual_dataset(name, lay)
                elif kind == "reference":
                    h5.create_dataset("refs", data=[h5["site"].ref, grp.ref],
                                      dtype=h5py.ref_dtype)
                elif kind == "reference-attr":
                    grp.attrs["pointer"] = h5["site"].ref
                else:  # 17 kB that would cost tens of GB: unallocated chunks
                    grp.create_dataset("zzz", shape=(10 ** 9, 3), dtype="f8", chunks=(4096, 3))
            out[f"{base}-{kind}"] = p
    return out


WHAT = {"external": ("is an external link to other.h5", "{grp}/{name}"),
        "virtual": ("is a virtual dataset (mapped from other.h5)", "{grp}/{name}"),
        "reference": ("holds HDF5 object or region references", "/refs"),
        "reference-attr": ("attribute 'pointer'", "{grp}"),
        "huge": ("declares 24 GB of data", "{grp}/zzz")}


def _commands(f, bad, base, d):
    if base == "raw":
        return {"fit": ["fit", "accel", bad, "--out", d / "o.h5"],
                "apply": ["apply", f["cal"], bad, "--out", d / "o.h5"],
                "show": ["show", bad]}
    return {"apply": ["apply", bad, f["raw"], "--out", d / "o.h5"],
            "show": ["show", bad, "--json"],
            "export": ["export", bad, "--format", "json", "--out", d / "o.json"]}


@pytest.mark.parametrize("base", ["raw", "cal"])
@pytest.mark.parametrize("kind", list(WHAT))
def test_hdf5_links_vds_references_refused(h5_files, base, kind, tmp_path):
    f = h5_files
    bad = f[f"{base}-{kind}"]
    grp, name = ("/samples", "accel") if base == "raw" else ("/params", "accel_K")
    what, obj = WHAT[kind]
    obj = obj.format(grp=grp, name=name)
    for cmd, args in _commands(f, bad, base, tmp_path).items():
        code, out, err = run_cli(*args)
        assert code == 3, (cmd, code, err)
        lines = err.strip().splitlines()
        assert len(lines) == 1, (cmd, err)
        assert str(bad) in lines[0] and what in lines[0] and obj in lines[0], (cmd, lines[0])
        assert "Traceback" not in err
        assert not list(tmp_path.glob("o*")), cmd  # nothing left behind
    # the same file without the addition is fine
    code, _, err = run_cli("show", f[base])
    assert code == 0, err


def test_hdf5_guard_is_in_open_checked(h5_files):
    """report and diagnose read through the same gate."""
    f = h5_files
    d = f["dir"]
    code, _, err = run_cli("report", f["cal-external"], "--out", d / "rep")
    assert code == 3 and "external link" in err
    code, _, err = run_cli("report", f["cal"], f["raw-virtual"], "--out", d / "rep")
    assert code == 3 and "virtual dataset" in err
    code, _, err = run_cli("diagnose", f["raw-reference"], "--method", "accel",
                           "--out", d / "dg.h5")
    assert code == 3 and "references" in err


# ---------------------------------------------------------------------------
# the Dask recipe of docs/batch.md listens on loopback only


def _recipe() -> list[list[str]]:
    text = (ROOT / "docs" / "batch.md").read_text(encoding="utf-8")
    cmds = [ln.strip() for ln in text.splitlines()
            if ln.strip().startswith(("dask scheduler --host 127.0.0.1",
                                      "dask worker tcp://127.0.0.1"))]
    assert len(cmds) == 2, cmds
    return [c.split() for c in cmds]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _listening(pids) -> list:
    import psutil

    found = []
    for pid in pids:
        try:
            procs = [psutil.Process(pid)]
            procs += procs[0].children(recursive=True)
        except psutil.NoSuchProcess:
            continue
        for p in procs:
            try:
                conns = (p.net_connections(kind="inet") if hasattr(p, "net_connections")
                         else p.connections(kind="inet"))
            except psutil.NoSuchProcess:
                continue
            found += [(p.pid, c.laddr.ip, c.laddr.port) for c in conns
                      if c.status == psutil.CONN_LISTEN or c.type == socket.SOCK_DGRAM]
    return found


def test_documented_dask_recipe_listens_on_loopback_only(tmp_path):
    pytest.importorskip("distributed")
    pytest.importorskip("psutil")
    from distributed import Client

    sched, work = _recipe()
    # the documented commands, with a free port for 8786 (other runs may share this machine)
    port = str(_free_port())
    sched = [a.replace("8786", port) for a in sched]
    work = [a.replace("8786", port) for a in work]
    assert sched[:2] == ["dask", "scheduler"] and work[:2] == ["dask", "worker"]
    dask_bin = Path(sys.executable).with_name("dask")
    env = dict(os.environ, DASK_TEMPORARY_DIRECTORY=str(tmp_path))
    procs = []
    try:
        for cmd in (sched, work):
            procs.append(subprocess.Popen([str(dask_bin), *cmd[1:]], cwd=tmp_path, env=env,
                                          stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                          start_new_session=True))
        n_workers = int(work[work.index("--nworkers") + 1]) if "--nworkers" in work else 1
        with Client(f"tcp://127.0.0.1:{port}", timeout="60s") as client:
            client.wait_for_workers(n_workers, timeout=90)
            assert client.submit(sum, [1, 2]).result(timeout=30) == 3
            # the client side (what `calib batch --scheduler` is) opens no listening socket
            mine = [s for s in _listening([os.getpid()]) if s[1] not in ("127.0.0.1", "::1")]
            assert not mine, mine
        time.sleep(1.0)  # dashboards and nannies are up once the workers registered
        socks = _listening([p.pid for p in procs])
        print("listening:", sorted({(ip, port) for _, ip, port in socks}))
        assert len(socks) >= 2 + 2 * n_workers  # scheduler + dashboard, worker + dashboard
        outside = [s for s in socks if s[1] not in ("127.0.0.1", "::1")]
        assert not outside, outside
    finally:
        for p in procs:  # the process groups started here, and nothing else
            with contextlib.suppress(ProcessLookupError):
                os.killpg(p.pid, signal.SIGTERM)
        for p in procs:
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(p.pid, signal.SIGKILL)
                p.wait(timeout=10)


def test_history_plot_and_table_with_hostile_serial_and_names(tmp_path):
    """calib history: the serial and the archive's file names reach a plot
    (mathtext) and the terminal (rich markup) as plain text."""
    serial = r"[/] $x^{$ " + HOSTILE[0]
    arch = tmp_path / "arch"
    arch.mkdir()
    for i, name in enumerate((r"$\undefinedcommand{x}$ [red].h5", "b [bold]\x1b[2J.h5")):
        write_calibration(arch / name, replace(triad_calibration(seed=i), serial=serial))
    code, out, err = run_cli("history", arch, "--unit", serial, "--plot", tmp_path / "h.png")
    assert code == 0, err
    assert (tmp_path / "h.png").stat().st_size > 1000
    assert "\x1b" not in out and "[/]" in out


def test_hdf5_refusal_is_one_line_whatever_the_names(h5_files, tmp_path):
    """The refused object's name and link target come from the file: the
    error stays one line and sends no escape sequence."""
    bad = tmp_path / "raw.h5"
    shutil.copy(h5_files["raw"], bad)
    with h5py.File(bad, "a") as h5:
        h5["samples"]["x\n\x1b]0;owned\x07y"] = h5py.ExternalLink("o\nther\x1b[2J.h5", "/a\nb")
    code, _, err = run_cli("fit", "accel", bad, "--out", tmp_path / "o.h5")
    assert code == 3 and len(err.strip().splitlines()) == 1, err
    assert "\x1b" not in err and "external link" in err and "\\x0a" in err
