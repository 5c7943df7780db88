"""Streaming CSV import (issue 19): same raw data, same segments, same error
messages as the in-memory reader, with pyarrow's reader and without it."""

from __future__ import annotations

import numpy as np
import pytest
from gyro_sim import simulated

from calib_cli.errors import InputError
from calib_cli.io.csvlog import have_pyarrow, import_csv, import_csv_stream, write_csv
from calib_cli.io.h5 import read_raw
from calib_cli.io.plan import parse_plan
from calib_cli.methods.static_detect import detect_static
from calib_cli.methods.static_stream import (
    detect_static_arrays,
    detect_static_stream,
    moving_std_blocks,
    stream_median_diff,
    stream_percentile,
)

MODES = [False] + ([True] if have_pyarrow() else [])


@pytest.fixture(scope="module")
def sim():
    rec, _ = simulated(7, False)
    return rec


def _blocks(rec, bs):
    def f():
        for i in range(0, len(rec.time), bs):
            yield rec.time[i:i + bs], rec.accel[i:i + bs], rec.gyro[i:i + bs]
    return f


@pytest.mark.parametrize("kw", [{}, {"min_duration_s": 9.0}, {"multiplier": 1.5},
                                {"window_s": 0.3}])
@pytest.mark.parametrize("bs", [777, 65536])
def test_stream_detector_same_intervals(sim, kw, bs):
    ref = detect_static(sim.time, sim.accel, sim.gyro, **kw)
    got = detect_static_stream(_blocks(sim, bs), len(sim.time), **kw)
    assert got.intervals == ref.intervals
    assert got.counts == ref.counts and got.short_runs == ref.short_runs
    assert np.allclose(got.floor_accel, ref.floor_accel, rtol=1e-6)
    assert np.allclose(got.floor_gyro, ref.floor_gyro, rtol=1e-6)
    assert got.static_fraction == pytest.approx(ref.static_fraction, abs=1e-12)
    assert got.explain(12) == ref.explain(12) or got.counts == ref.counts
    arr = detect_static_arrays(sim.time, sim.accel, sim.gyro, rows=bs, **kw)  # import text's
    assert arr.intervals == ref.intervals and arr.counts == ref.counts


def test_stream_quantiles_exact():
    from calib_cli.methods import static_stream as ss
    from calib_cli.methods.static_detect import moving_std

    rng = np.random.default_rng(1)
    x = rng.normal(size=(10007, 3)) + np.repeat(rng.normal(size=(11, 3)) * 10, 910, axis=0)[:10007]
    for w in (3, 101, 2000):
        got = np.concatenate(list(moving_std_blocks((x[i:i + 999] for i in range(0, len(x), 999)),
                                                    w, len(x))))
        assert np.allclose(got, moving_std(x, w), rtol=1e-6, atol=1e-9)
    for q in (10, 50):
        def blocks():
            return (x[i:i + 700] for i in range(0, len(x), 700))
        assert np.array_equal(stream_percentile(blocks, len(x), q), np.percentile(x, q, axis=0))
    # a bracket too full for memory: narrowed by a histogram pass first, still exact
    old = ss.BRACKET_CAP
    ss.BRACKET_CAP = 50
    try:
        assert np.array_equal(stream_percentile(blocks, len(x), 10), np.percentile(x, 10, axis=0))
        # ties: a regular clock's steps differ in their last bits only, or not at all
        tr = np.round(np.arange(20000) * 0.001, 6)
        assert stream_median_diff(lambda: (tr[i:i + 999] for i in range(0, len(tr), 999)),
                                  len(tr)) == np.median(np.diff(tr))
        tq = np.arange(20000) * 0.25
        assert stream_median_diff(lambda: (tq[i:i + 999] for i in range(0, len(tq), 999)),
                                  len(tq)) == 0.25
    finally:
        ss.BRACKET_CAP = old
    t = np.cumsum(rng.uniform(0.9, 1.1, 5000))
    assert stream_median_diff(lambda: (t[i:i + 333] for i in range(0, len(t), 333)),
                              len(t)) == np.median(np.diff(t))


def _nosegment_csv(sim, path, comments=False, crlf=False):
    write_csv(path, sim)
    lines = path.read_text().splitlines()
    rows = [lines[0]] + [",".join(r.split(",")[:-1]) for r in lines[1:]]
    if comments:  # comment lines anywhere, blank lines, indented comments
        for i in (50, 5000, 9001, len(rows) - 3):
            rows.insert(i, "  # a note in the middle" if i % 2 else "# note")
        rows.insert(7000, "")
    path.write_text(("\r\n" if crlf else "\n").join(rows) + "\n")
    return path


@pytest.mark.parametrize("fast", MODES)
@pytest.mark.parametrize("comments,crlf", [(False, False), (True, False), (True, True)])
def test_stream_import_equals_in_memory(tmp_path, sim, fast, comments, crlf):
    plan = parse_plan(sim.plan_text)
    csv = _nosegment_csv(sim, tmp_path / "log.csv", comments, crlf)
    ref = import_csv(csv, plan)
    res = import_csv_stream(csv, plan, tmp_path / "raw.h5", [csv], fast=fast)
    got = read_raw(tmp_path / "raw.h5")
    assert res.n == len(ref)
    assert np.array_equal(got.time, ref.time) and np.array_equal(got.accel, ref.accel)
    assert np.array_equal(got.gyro, ref.gyro)
    assert [(s.label, s.start, s.stop) for s in got.segments] == \
        [(s.label, s.start, s.stop) for s in ref.segments]


@pytest.mark.parametrize("fast", MODES)
def test_stream_import_segment_column(tmp_path, sim, fast):
    plan = parse_plan(sim.plan_text)
    write_csv(tmp_path / "log.csv", sim)
    ref = import_csv(tmp_path / "log.csv", plan)
    import_csv_stream(tmp_path / "log.csv", plan, tmp_path / "raw.h5", fast=fast)
    got = read_raw(tmp_path / "raw.h5")
    assert [(s.label, s.start, s.stop, s.plan_index) for s in got.segments] == \
        [(s.label, s.start, s.stop, s.plan_index) for s in ref.segments]
    assert np.array_equal(got.temp, ref.temp) if ref.temp is not None else got.temp is None


H = "time,ax,ay,az,gx,gy,gz\n"
BAD = [
    "time,ax,ay,gx,gy,gz\n0,1,2,3,4,5\n",
    H + "0,1,2,3,4,5,6\n0.01,1,x2,3,4,5,6\n",
    H + "0,1,2,3,4,5,6\n0.01,1,nan,3,4,5,6\n",
    H + "0,1,2,3,4,5,6\n0.01,1,nan,3,4,5,6\n0.02,1,2,3\n",  # the bad row wins over NaN
    H + "0,1,2,3,4,5,6\n0,1,2,3,4,5,6\n",
    H + "0,1,2,3,4,5,6\n#c\n0.01,1,2,3,4,5,6\n0.005,1,2,3,4,5,6\n",
    H + "0,1,2,3,4,5,6\n0.01,1,2,3,4,5,6,7\n",
    H + "0,1,2,3,4,5,6\n0.01,1,,3,4,5,6\n",
    "time,ax,ay,az,gx,gy,gz,segment\n0,1,2,3,4,5,6,0.5\n0.01,1,2,3,4,5,6,0\n",
    "time,ax,ay,az,gx,gy,gz,segment\n0,1,2,3,4,5,6,99\n0.01,1,2,3,4,5,6,0\n",
    "time,ax,ay,az,gx,gy,gz,time\n0,1,2,3,4,5,6,0\n",
    "time,ax,ay,gx,gy,gz\n0,1,2,3,4,5\n0.1,x,1,1,1,1\n",  # the bad cell wins over the column
    "", "# only a comment\n", H, H + "# nothing but comments\n",
]


@pytest.mark.parametrize("fast", MODES)
@pytest.mark.parametrize("body", BAD)
def test_stream_errors_as_before(tmp_path, sim, fast, body):
    plan = parse_plan(sim.plan_text)
    p = tmp_path / "bad.csv"
    p.write_text(body)
    with pytest.raises(InputError) as ref:
        import_csv(p, plan)
    with pytest.raises(InputError) as got:
        import_csv_stream(p, plan, tmp_path / "raw.h5", fast=fast)
    assert str(got.value) == str(ref.value)
    assert not (tmp_path / "raw.h5").exists()


def test_stream_errors_across_blocks(tmp_path, sim, monkeypatch):
    """Line numbers and row numbers count across the reader's blocks."""
    import calib_cli.io.csvlog as csvlog

    monkeypatch.setattr(csvlog, "STREAM_ROWS", 1000)
    plan = parse_plan(sim.plan_text)
    csv = _nosegment_csv(sim, tmp_path / "log.csv", comments=True)
    lines = csv.read_text().splitlines()
    for edit in (lambda r: r.replace(",", ",x", 1), lambda r: r + ",9",
                 lambda r: "0.0," + r.split(",", 1)[1]):
        mod = list(lines)
        mod[4321] = edit(mod[4321])
        (tmp_path / "m.csv").write_text("\n".join(mod) + "\n")
        with pytest.raises(InputError) as ref:
            import_csv(tmp_path / "m.csv", plan)
        for fast in MODES:
            with pytest.raises(InputError) as got:
                import_csv_stream(tmp_path / "m.csv", plan, tmp_path / "r.h5", fast=fast)
            assert str(got.value) == str(ref.value)


H_TEXT = ["time,ax,ay,az,gx,gy,gz\n0,1,2,3,4,5,6\n0.01,1,2,3,4,5,6\n",
          "t;acc_x;acc_y;acc_z\n0;1;2;3\n0.01;1;2;3\n",
          "0,1,2,3,4,5,6\n0.01,1,2,3,4,5,6\n"]


@pytest.mark.parametrize("body", H_TEXT + ['time,ax,ay,az\n0,1,2,3\n0.01,"1",2,3\n',
                                           "time,ax,ay,az\n0,1,2,3\n%c\n0.01,1,2,3\n",
                                           "time,ax,ay,az\n0,1,2,3\n0.01,1,nan,3\n"])
def test_text_fast_reader_same_as_reference(tmp_path, body):
    """import text: pyarrow's reader gives the reference reader's numbers, or
    leaves the file to it."""
    from calib_cli.io.textlog import read_text

    p = tmp_path / "x.txt"
    p.write_text(body)
    ref = read_text(str(p), fast=False)
    got = read_text(str(p))
    assert got[0] == ref[0] and np.array_equal(got[2], ref[2])
    if got[1].dtype != object:
        assert np.array_equal(got[1], ref[1].astype(float))
    else:
        assert np.array_equal(got[1], ref[1])


def test_plan_layout_same_as_simulator():
    from pathlib import Path

    from calib_cli.io.plan import load_plan
    from calib_cli.plan import plan_layout
    from calib_cli.sim import simulate

    root = Path(__file__).resolve().parents[1] / "sample_data"
    for name in ("twelve_position.toml", "rimu_six_position.toml"):
        plan = load_plan(root / name)
        a, b = plan_layout(plan), simulate.plan_layout(plan)
        assert a.n == b.n and a.n_cycles == b.n_cycles
        assert np.array_equal(a.el0, b.el0) if a.el0 is not None else b.el0 is None


@pytest.mark.parametrize("fast", MODES)
def test_stream_import_rotating_plan_same_segments(tmp_path, fast):
    """A turntable plan without a segment column: the rotation cycles
    (methods/cycle_detect.py) give the same segments streamed or in memory."""
    from test_plan_semantics import CONTRACT_TT

    from calib_cli.sim.simulate import simulate

    plan = parse_plan(CONTRACT_TT)
    rec = simulate(plan, None, 4)
    write_csv(tmp_path / "log.csv", rec)
    lines = (tmp_path / "log.csv").read_text().splitlines()
    hdr = next(i for i, ln in enumerate(lines) if not ln.startswith("#"))
    j = lines[hdr].split(",").index("segment")
    (tmp_path / "noseg.csv").write_text("\n".join(
        lines[:hdr] + [",".join(p for k, p in enumerate(ln.split(",")) if k != j)
                       for ln in lines[hdr:]]) + "\n")
    ref = import_csv(tmp_path / "noseg.csv", plan)
    import_csv_stream(tmp_path / "noseg.csv", plan, tmp_path / "raw.h5", fast=fast)
    got = read_raw(tmp_path / "raw.h5")
    assert [(s.kind, s.start, s.stop) for s in got.segments] == \
        [(s.kind, s.start, s.stop) for s in ref.segments]
    assert [s.kind for s in got.segments] == ["rotating"] * 3


TEXT_LAYOUTS = [  # (columns of the file, header, separator, import_text options)
    (lambda s: [s.time * 1e3, np.degrees(s.gyro), s.accel / 9.80665],
     ["ms", "Gx", "Gy", "Gz", "Ax", "Ay", "Az"], ",",
     dict(columns="time=ms,ax=Ax,ay=Ay,az=Az,gx=Gx,gy=Gy,gz=Gz", accel_units="g",
          gyro_units="deg/s", time_unit="ms")),
    (lambda s: [s.time, s.accel, s.gyro], None, ";", {}),
    (lambda s: [s.accel, s.gyro], None, "\t", dict(rate=100.0)),
    (lambda s: [np.arange(len(s.time)), s.accel, s.gyro, 20 + s.time * 0.01],
     ["sample", "acc_x", "acc_y", "acc_z", "gyr_x", "gyr_y", "gyr_z", "temperature"], ",",
     dict(rate=100.0)),
]


@pytest.mark.skipif(not have_pyarrow(), reason="the streamed text reader needs pyarrow")
@pytest.mark.parametrize("layout", range(len(TEXT_LAYOUTS)))
def test_text_streamed_equals_in_memory(tmp_path, sim, layout, monkeypatch):
    """import text: a single delimited file goes through the streaming pipeline
    and gives the in-memory import's samples, units and segments."""
    from calib_cli.io import textlog
    from calib_cli.io.textlog import import_text, import_text_to_raw

    cols, header, sep, kw = TEXT_LAYOUTS[layout]
    p = tmp_path / "log.txt"
    with open(p, "w") as fh:
        fh.write("# a comment before the header\n")
        if header:
            fh.write(sep.join(header) + "\n")
        np.savetxt(fh, np.column_stack(cols(sim)), delimiter=sep, fmt="%.9g")
    plan = parse_plan(sim.plan_text)
    ref = import_text(p, plan, **kw)
    called = []
    real = textlog.import_text
    monkeypatch.setattr(textlog, "import_text", lambda *a, **k: called.append(1) or real(*a, **k))
    n, units, segs = import_text_to_raw(tmp_path / "raw.h5", p, plan, inputs=[p], **kw)
    assert not called  # streamed, not the in-memory path
    got = read_raw(tmp_path / "raw.h5")
    assert n == len(ref) and units == ref.units
    assert np.array_equal(got.time, ref.time) and np.array_equal(got.accel, ref.accel)
    assert np.array_equal(got.gyro, ref.gyro)
    assert (got.temp is None) == (ref.temp is None)
    if ref.temp is not None:
        assert np.array_equal(got.temp, ref.temp)
    assert [(s.label, s.start, s.stop) for s in got.segments] == \
        [(s.label, s.start, s.stop) for s in ref.segments]


@pytest.mark.parametrize("body,match", [
    ("time,ax,ay,az\n0,1,2,3\n0.01,1,x,3\n", "line 3, column 'ay': not a number"),
    ("time,ax,ay,az\n0,1,2,3\n# c\n0.01,1,2\n", "line 4: 3 cells, expected 4"),
    ("time,ax,ay,az\n0.02,1,2,3\n0.01,1,2,3\n", "time is not increasing at line 3"),
    ("time,ax,ay,az\n", "no data rows"),
])
def test_text_streamed_errors_from_the_in_memory_path(tmp_path, body, match):
    from calib_cli.io.textlog import import_text_to_raw

    p = tmp_path / "bad.csv"
    p.write_text(body)
    with pytest.raises(InputError, match=match):
        import_text_to_raw(tmp_path / "raw.h5", p, parse_plan(
            'name = "h"\nkind = "static"\n[[segment]]\nlabel = "pos"\nrepeat = "auto"\n'))
    assert not (tmp_path / "raw.h5").exists()


@pytest.mark.parametrize("case", ["first_bracket", "narrowed", "fallback"])
def test_online_floors_same_report(sim, case, monkeypatch):
    """The import's detector without a spill (OnlineFloors): the same report,
    bit for bit, as the passes over the whole moving std (ListStore); when
    its bracket is narrowed on the way; and through the fallback (the moving
    std computed again) when the bracket misses the floor."""
    from calib_cli.methods import static_stream as ss

    if case == "narrowed":
        monkeypatch.setattr(ss, "BRACKET_CAP", 2000)
    if case == "fallback":
        monkeypatch.setattr(ss, "ONLINE_PAD", 0.0)  # a first bracket of one rank or so
        monkeypatch.setattr(ss.OnlineFloors, "_bracket", _tiny_bracket(ss.OnlineFloors._bracket))
    bs = 4096
    reps = []
    for store in (ss.OnlineFloors(3.0), ss.ListStore()):
        det = ss.StreamDetector(1.0, store)
        for i in range(0, len(sim.time), bs):
            det.feed(sim.time[i:i + bs], sim.accel[i:i + bs], sim.gyro[i:i + bs])
        reps.append(det.result(_blocks(sim, bs), 3.0, 1.0))
        if isinstance(store, ss.OnlineFloors):
            used = store.result(len(sim.time), 3.0) is not None
            assert used == (case != "fallback")
    got, ref = reps
    assert got.intervals == ref.intervals and got.counts == ref.counts
    assert got.short_runs == ref.short_runs and got.static_fraction == ref.static_fraction
    if case != "fallback":  # the same moving std: the same floors, bit for bit
        assert np.array_equal(got.floor_accel, ref.floor_accel)
        assert np.array_equal(got.floor_gyro, ref.floor_gyro)
    else:
        assert np.allclose(got.floor_accel, ref.floor_accel, rtol=1e-9)


def _tiny_bracket(orig):
    def bracket(self, s):
        orig(self, s)
        self.hi = self.lo.copy()  # a bracket that holds no floor but the first block's
        self.hi0 = np.maximum(self.hi, 1e-300)
        self.inv_min = 1.0 / self.hi0
    return bracket


@pytest.mark.parametrize("shift", [1.0, 50.0])
def test_online_floors_exact_or_gives_up(monkeypatch, shift):
    """Narrowed brackets give np.percentile's floor exactly; data whose level
    shifts after the first block (the floor outside every bracket) make the
    store give up (None), never a wrong floor."""
    from calib_cli.methods import static_stream as ss

    monkeypatch.setattr(ss, "BRACKET_CAP", 500)
    rng = np.random.default_rng(3)
    blocks = [np.asfortranarray(np.abs(rng.normal(size=(1000, 2))) * (1.0 if i == 0 else shift))
              for i in range(10)]
    store = ss.OnlineFloors(3.0)
    for b in blocks:
        store.write(b)
    got = store.result(10000, 3.0)
    ref = np.percentile(np.concatenate(blocks), ss.FLOOR_QUANTILE, axis=0)
    if shift == 1.0:
        assert got is not None and np.array_equal(got[0], ref)
    else:
        assert got is None or np.array_equal(got[0], ref)
