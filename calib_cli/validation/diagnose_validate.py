"""Many-case validation of ``calib diagnose`` (run by tests/test_diagnose_slow.py,
`make validate`; writes docs/diagnose-validation.md).

    python -m calib_cli.validation.diagnose_validate N OUT.md
"""

from __future__ import annotations

import sys
import time

import numpy as np

from calib_cli.methods.diagnose import diagnose
from calib_cli.methods.rimu import segment_kinematics
from calib_cli.model.kinematics import rigid_body_accel
from calib_cli.sim.simulate import simulate
from calib_cli.validation import diagnose_cases as C


def case_rates(case: str | None, n: int, method: str | None = None, seed0: int = 1000) -> dict:
    """Rates over n seeds: named first, final RMS within 1.2x the floor, nothing added."""
    first, gap_ok, clean, steps, t0 = 0, 0, 0, [], time.time()
    wrong = {}
    for k in range(n):
        d = C.run_case(case, seed0 + 7 * k, method=method)
        key = C.first_key(d)
        if case is not None and key == C.expected(case):
            first += 1
        elif case is not None:
            wrong[str(key)] = wrong.get(str(key), 0) + 1
        if d.residual_rms_final <= 1.2 * d.noise_rms:
            gap_ok += 1
        if not d.steps:
            clean += 1
        steps.append(len(d.steps))
    return {"case": case or f"none ({method})", "n": n, "named_first": first / n,
            "gap_ok": gap_ok / n, "nothing_added": clean / n, "mean_steps": float(np.mean(steps)),
            "wrong": wrong, "seconds": time.time() - t0}


# -- effects in a form the catalogue does not have -------------------------


def out_of_catalogue(kind: str, seed: int):
    """Diagnose data with an effect outside the catalogue's forms:
    "cubic" (accel y += k3 u^3), "thermal" (accel bias quadratic in T),
    "slip" (the lever arm jumps half-way through each rotating cycle)."""
    rng = np.random.default_rng(seed)
    if kind in ("cubic", "thermal"):
        plan = C.plan_of("accel")
        rec = simulate(plan, C._base_truth(plan, rng, "full"), seed=seed + 1)
        acc = rec.accel.copy()
        if kind == "cubic":  # at constant temperature: the positions alone tell the form
            k3 = rng.choice([-1, 1], 3) * rng.uniform(4e-6, 6e-6, 3)  # 1/(m/s^2)^2
            acc += k3 * acc ** 3
            rec = rec.with_(temp=None)
        else:
            c = rng.choice([-1, 1], 3) * rng.uniform(2e-5, 4e-5, 3)  # m/s^2/degC^2
            acc += np.outer((rec.temp - 27.0) ** 2, c)
        return diagnose(rec.with_(accel=acc), "accel")
    plan = C.plan_of("turntable")
    rec = simulate(plan, C._base_truth(plan, rng, "full"), seed=seed + 1)
    acc = rec.accel.copy()
    s1 = rng.normal(0, 1, 3) * 2e-3
    s2 = s1 + rng.normal(0, 1, 3) * 1e-3  # the unit slips by about 1 mm
    for seg in rec.segments:
        if seg.kind != "rotating":
            continue
        kin = segment_kinematics(rec, seg)
        half = len(kin) // 2
        s = np.where((np.arange(len(kin)) < half)[:, None], s1, s2)
        acc[seg.slice] += rigid_body_accel(kin.w, kin.dw, s)
    return diagnose(rec.with_(accel=acc), "turntable")


def table(rows: list[dict]) -> str:
    lines = ["| hidden effect | cases | named first | final RMS <= 1.2x floor | nothing added "
             "| mean steps | named first instead (count) | s |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        wrong = ", ".join(f"{k} {v}" for k, v in sorted(r["wrong"].items())) or "-"
        nf = "-" if r["case"].startswith("none") else f"{100 * r['named_first']:.1f} %"
        if r["case"] in C.REPORTED_ONLY:
            nf += " (reported, not asserted)"
        lines.append(f"| {r['case']} | {r['n']} | {nf} | {100 * r['gap_ok']:.1f} % | "
                     f"{100 * r['nothing_added']:.1f} % | {r['mean_steps']:.2f} | {wrong} | "
                     f"{r['seconds']:.0f} |")
    return "\n".join(lines)


def _row(job):
    case, n, method = job
    return case_rates(case, n, method=method)


def run_all(n: int, workers: int = 1) -> tuple[list[dict], str]:
    """Every case and the no-effect rows of each method, on ``workers`` processes."""
    jobs = [(c, n, None) for c in C.CASES]
    jobs += [(None, n, m) for m in ("accel", "turntable", "rimu", "align")]
    if workers > 1:
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(workers) as ex:
            rows = list(ex.map(_row, jobs))
    else:
        rows = [_row(j) for j in jobs]
    return rows, table(rows)


if __name__ == "__main__":
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 40
    rows, md = run_all(n)
    print(md)
    if len(sys.argv) > 2:
        open(sys.argv[2], "w").write(md + "\n")


# -- the real recordings (shared/datasets) ---------------------------------


def _xsens(root):
    from pathlib import Path

    from calib_cli.io.plan import parse_plan
    from calib_cli.io.textlog import import_text
    from calib_cli.validation.validate_datasets import XSENS_PLAN

    d = Path(root) / "imu_tk_xsens_mti"
    return import_text(d / "xsens_acc.mat", parse_plan(XSENS_PLAN, "xsens.toml"),
                       d / "xsens_gyro.mat", accel_units="count", gyro_units="count")


def _ferraris(root):
    from pathlib import Path

    from calib_cli.io.plan import parse_plan
    from calib_cli.io.textlog import import_text
    from calib_cli.validation.validate_datasets import ferraris_plan

    d = Path(root) / "imucal_ferraris"
    return import_text(d / "annotated_session.csv", parse_plan(ferraris_plan(360.0)),
                       columns="time=samples,ax=acc_x,ay=acc_y,az=acc_z,gx=gyr_x,gy=gyr_y,"
                               "gz=gyr_z,segment=part",
                       accel_units="count", gyro_units="count", rate=204.8,
                       time_unit="sample", sort=True)


def _keep_segments(rec, keep):
    """The recording with only the static segments whose index is in ``keep``."""
    segs = tuple(s for i, s in enumerate(rec.segments) if i in keep)
    return rec.with_(segments=segs)


def real_datasets(root) -> list[dict]:
    """Diagnose the real recordings; for the Xsens (38 positions) also each half of
    the positions on its own, and with white (high-frequency) noise weights, to see
    whether the evidence holds up."""
    from calib_cli.methods.diagnose_candidates import effect_key

    out = []

    def row(name, rec, noise="auto"):
        d = diagnose(rec, "accel", noise=noise)
        j = d.to_json()
        out.append({"data": name, "noise": noise, "positions": int(len(set(d.problem.bin_seg))),
                    "steps": [(effect_key(s.effect, s.sensor), round(s.score, 1),
                               round(s.threshold, 1), s.evidence) for s in d.steps],
                    "rms0": d.residual_rms_initial, "rms1": d.residual_rms_final,
                    "floor": d.noise_rms, "scatter": j["bin_scatter_ratio"]["accel"],
                    "untested": d.untested, "diag": d})

    xs = _xsens(root)
    row("xsens (38 positions, attitudes unknown)", xs)
    row("xsens", xs, noise="hf")
    idx = [i for i, s in enumerate(xs.segments) if s.kind == "static"]
    row("xsens, odd positions", _keep_segments(xs, set(idx[0::2])))
    row("xsens, even positions", _keep_segments(xs, set(idx[1::2])))
    fe = _ferraris(root)
    row("ferraris annotated (6 positions)", fe)
    row("ferraris annotated", fe, noise="hf")
    return out


def real_table(rows: list[dict]) -> str:
    lines = ["| recording | noise | positions | steps (score / threshold) | RMS base -> final "
             "| floor | bin scatter ratio |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        st = "; ".join(f"{k} ({s:.0f} / {t:.1f})" for k, s, t, _ in r["steps"]) or "none"
        sc = ", ".join(f"{x:.2f}" for x in r["scatter"])
        lines.append(f"| {r['data']} | {r['noise']} | {r['positions']} | {st} | "
                     f"{r['rms0']:.2f} -> {r['rms1']:.2f} | {r['floor']:.2f} | {sc} |")
    return "\n".join(lines)
