"""Issue 37: `calib diagnose` on every method and plan size ends in exit 0, 3 or 4
with one line naming the file, never an internal error (an 18-cycle rimu plan
gave exit 70: more lever-arm conventions than observable entries).

The catalogue of plan families (`calib plan make`, and an 18-cycle tilted rimu
plan) x the five methods x segment counts. `make test` runs the combinations
that take seconds; `make validate K=diagnose_sizes` all of them."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.hand_plans import rimu18_plan

ROOT = Path(__file__).resolve().parents[1]
METHODS = ("accel", "gyro", "align", "turntable", "rimu")

PLANS = {  # name -> `calib plan make` arguments (short segments: the matrix stays fast)
    "static6": ["static", "--positions", "6", "--duration", "2", "--rate", "50"],
    "static24": ["static", "--positions", "24", "--duration", "2", "--rate", "50"],
    "scalar12": ["static", "--positions", "12", "--fit", "scalar", "--duration", "2",
                 "--rate", "50"],
    "ferraris": ["ferraris", "--duration", "2", "--rate", "50"],
    "align": ["align", "--duration", "5", "--rate", "20"],
    "rimu6": ["rimu", "--duration", "2", "--rate", "50"],
    "rimu18": None,  # 18 rotating segments at tilted attitudes (below)
}
# combinations that take tens of seconds (a full diagnosis): make validate only
SLOW = {("static6", "gyro"), ("static24", "align"), ("static24", "gyro"), ("scalar12", "gyro"),
        ("ferraris", "gyro"), ("rimu18", "rimu"), ("rimu6", "rimu"), ("scalar12", "align"),
        ("static6", "align")}


def _cli(*args):
    import contextlib
    import io

    from calib_cli.cli.main import main

    err = io.StringIO()
    code = 0
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            main(["-q", *[str(a) for a in args]])
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else 0
    return code, err.getvalue()


def _rimu18(path: Path) -> None:
    path.write_text(rimu18_plan())


@pytest.fixture(scope="module")
def records(tmp_path_factory):
    d = tmp_path_factory.mktemp("dsizes")
    out = {}
    for name, args in PLANS.items():
        plan = d / f"{name}.toml"
        if args is None:
            _rimu18(plan)
        else:
            code, err = _cli("plan", "make", *args, "--out", plan)
            assert code == 0, (name, err)
        code, err = _cli("simulate", plan, "--out", d / f"{name}.h5", "--seed", "1")
        assert code == 0, (name, err)
        out[name] = d / f"{name}.h5"
    return out


CASES = [pytest.param(p, m, marks=[pytest.mark.slow, pytest.mark.part("diagnose_sizes")])
         if (p, m) in SLOW else (p, m) for p in PLANS for m in METHODS]


@pytest.mark.parametrize("plan,method", CASES)
def test_diagnose_every_method_and_size(records, tmp_path, plan, method):
    raw = records[plan]
    code, err = _cli("diagnose", raw, "--method", method, "--out", tmp_path / "d.h5")
    lines = [x for x in err.splitlines() if x.strip() and not x.startswith("calib: warning")]
    assert code in (0, 3, 4), (plan, method, code, err[-500:])
    if code:
        assert len(lines) == 1 and raw.name in lines[0], (plan, method, lines)
        assert not (tmp_path / "d.h5").exists()
    else:
        assert (tmp_path / "d.h5").exists()
