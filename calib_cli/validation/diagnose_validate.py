"""Many-case validation of ``calib diagnose`` (run by tests/test_diagnose_slow.py,
`make validate`; writes docs/validation/diagnose.md).

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
    first, gap_ok, clean, steps, t0 = 0, 0, 0, [], time.process_time()
    reported, pair = 0, 0
    wrong, ratios, bounds = {}, [], []
    for k in range(n):
        d = C.run_case(case, seed0 + 7 * k, method=method)
        key = C.first_key(d)
        if case is not None and key == C.expected(case):
            first += 1
        elif case is not None:
            wrong[str(key)] = wrong.get(str(key), 0) + 1
            # named the other of a pair the diagnosis reports as not separable on this plan
            if any("not separable" in s and C.expected(case).split()[-1] in s
                   for s in d.notes):
                pair += 1
        ratios.append(float(d.residual_rms_final / d.noise_rms))
        # 1.05x, or for a fit of few equations (the gyro method) the chi^2 99 % point
        st = d.results[-1].stats if hasattr(d, "results") else None
        bounds.append(gap_bound(int(st["dof"]) if st is not None else None))
        if d.residual_rms_final <= 1.2 * d.noise_rms:
            gap_ok += 1
            reported += 1
        elif d.final_p_value < 0.01 and any("leaves" in s for s in d.notes):
            reported += 1  # the gap left is said, not called the noise floor
        if not d.steps:
            clean += 1
        steps.append(len(d.steps))
    return {"case": case or f"none ({method})", "n": n, "named_first": first / n,
            "gap_ok": gap_ok / n, "nothing_added": clean / n, "mean_steps": float(np.mean(steps)),
            "wrong": wrong, "gap_reported": reported / n, "seconds": time.process_time() - t0,
            "not_separable": pair / n,
            # per seed: final residual RMS / noise floor (issue 18: within 1.05x)
            "ratios": ratios, "ratio_max": float(np.max(ratios)),
            "within_105": float(np.mean(np.asarray(ratios) <= 1.05)),
            "bounds": bounds, "within_bound": float(np.mean(np.asarray(ratios)
                                                            <= np.asarray(bounds)))}


# -- effects in a form the catalogue does not have -------------------------


def out_of_catalogue(kind: str, seed: int):
    """Diagnose data with an effect outside the catalogue's forms:
    "cubic" (accel y += k3 u^3), "thermal" (accel bias quadratic in T),
    "slip" (the lever arm jumps half-way through each rotating cycle)."""
    rng = np.random.default_rng(seed)
    if kind in ("cubic", "thermal"):
        plan = C.plan_of("accel")
        rec = simulate(plan, C.base_truth(plan, rng, "full"), seed=seed + 1)
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
    rec = simulate(plan, C.base_truth(plan, rng, "full"), seed=seed + 1)
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
    """The rates table; per seed the final residual RMS / noise floor: its largest value,
    the share within 1.05x and, for the gyro method (a fit of ~70 equations, where
    sqrt(chi^2 / dof) scatters by ~9 %), the share within the chi^2 99 % point."""
    gyro = any(r.get("bounds") and max(r["bounds"]) > 1.05 for r in rows)
    lines = ["| hidden effect | cases | named first | final RMS <= 1.2x floor | nothing added "
             "| mean steps | named first instead (count) | max final / floor | <= 1.05x "
             + ("| within chi^2 99 % (bound) " if gyro else "") + "| CPU s |",
             "|---|---|---|---|---|---|---|---|---|" + ("---|" if gyro else "") + "---|"]
    for r in rows:
        wrong = ", ".join(f"{k} {v}" for k, v in sorted(r["wrong"].items())) or "-"
        nf = "-" if r["case"].startswith("none") else f"{100 * r['named_first']:.1f} %"
        if r["case"] in C.REPORTED_ONLY:
            nf += " (reported, not asserted)"
        mx = f"{r['ratio_max']:.3f}" if "ratio_max" in r else "-"
        w5 = f"{100 * r['within_105']:.1f} %" if "within_105" in r else "-"
        wb = ""
        if gyro:
            wb = (f"{100 * r['within_bound']:.1f} % ({min(r['bounds']):.2f}-"
                  f"{max(r['bounds']):.2f}) | " if r.get("bounds") else "- | ")
        label = r["case"] + (" (previous update's run)" if r.get("previous") else "")
        lines.append(f"| {label} | {r['n']} | {nf} | {100 * r['gap_ok']:.1f} % | "
                     f"{100 * r['nothing_added']:.1f} % | {r['mean_steps']:.2f} | {wrong} | "
                     f"{mx} | {w5} | {wb}{r['seconds']:.0f} |")
    return "\n".join(lines)


def _row(job):
    case, n, method = job[:3]
    cache = job[3] if len(job) > 3 else None
    path = _cache_path(cache, case, n, method)
    if path is not None and path.is_file():
        import json

        return json.loads(path.read_text())
    row = case_rates(case, n, method=method)
    if path is not None:  # a finished row survives an interrupted run
        import json

        path.write_text(json.dumps(row))
    return row


def _cache_path(cache, case, n, method):
    """Where a finished row is kept (``run_all(cache=DIR)``, CALIB_DIAG_CACHE), or None."""
    if not cache:
        return None
    import re
    from pathlib import Path

    Path(cache).mkdir(parents=True, exist_ok=True)
    name = re.sub(r"[^A-Za-z0-9]+", "_", case or f"none {method}")
    return Path(cache) / f"{name}-{n}.json"


HEADER = "# calib diagnose: validation"


def write_section(path, name: str, text: str) -> None:
    """Replace the part ``name`` of the generated document (between its begin/end
    comments; appended when missing), so each `make validate` part rewrites its own."""
    from pathlib import Path

    path = Path(path)
    old = path.read_text(encoding="utf-8") if path.is_file() else ""
    if not old.strip():
        old = (f"{HEADER}\n\nGenerated in parts by `make validate K=...` (docs/diagnose.md, "
               "\"Validation parts\"); each part rewrites its own section.\n")
    begin, end = f"<!-- begin {name} -->", f"<!-- end {name} -->"
    block = f"{begin}\n{text.rstrip()}\n{end}"
    if begin in old and end in old:
        head, rest = old.split(begin, 1)
        new = head + block + rest.split(end, 1)[1]
    else:
        new = old.rstrip("\n") + "\n\n" + block + "\n"
    path.write_text(new, encoding="utf-8")


def _cost(job) -> float:
    method = C.CASES[job[0]][0] if job[0] else job[2]
    return {"rimu": 4.0, "align": 2.5, "turntable": 1.0}.get(method, 0.5)


def run_all(n: int, workers: int = 1, cases=None, methods=("accel", "turntable", "rimu", "align"),
            cache=None) -> tuple[list[dict], str]:
    """Every case (default: all but the gyro method's) and the no-effect rows of
    each method, on ``workers`` processes. ``cache``: a directory where each finished
    row is kept and from where a re-run takes it (an interrupted run resumes)."""
    jobs = [(c, n, None, cache) for c in (C.MAIN_CASES if cases is None else cases)]
    jobs += [(None, n, m, cache) for m in methods]
    if workers > 1:
        from concurrent.futures import ProcessPoolExecutor

        order = sorted(range(len(jobs)), key=lambda i: -_cost(jobs[i]))  # longest first
        with ProcessPoolExecutor(workers) as ex:
            got = dict(zip(order, ex.map(_row, [jobs[i] for i in order])))
        rows = [got[i] for i in range(len(jobs))]
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


# -- fit --with against the truth (tests/test_fit_with_slow.py) ----------------

WANDER = ("bias_random_walk", "bias_instability")


def fit_with_z(job):
    """One seed of a case: (case, seed, normalised errors of the effect's entries,
    residual / floor, fitted / true of a wander, CPU s)."""
    from calib_cli.methods.fit_with import fit_with, fit_with_gyro

    case, seed = job
    t0 = time.process_time()
    method, name, sensor, base = C.CASES[case]
    rng = np.random.default_rng(seed)
    truth = C.hidden_effect_truth(case, rng)
    rec = simulate(C.plan_of(method), truth, seed=seed + 1)
    if method == "gyro":
        res = fit_with_gyro(rec, [(name, sensor)], base=base)
        layout = rec.layout
        st = res.stats
        gap = float(np.sqrt(st["chi2"] / max(st["dof"], 1)))
        dof = int(st["dof"])
        axes = None
    else:
        res, pb, _ = fit_with(rec, method, [(name, sensor)], base=base)
        layout = pb.layout
        gap = res.stats["residual_rms_noise_units"] / res.stats["noise_rms"]
        dof = None
        axes = pb.cycle_axes if method in ("turntable", "rimu") else None
    if name in WANDER:
        nm = res.stats["noise_model"]
        (key, vals), = next(iter(nm.values()))["params"].items()
        # what the Allan bounds of the record need (tests/test_fit_with_slow.py)
        plan = C.plan_of(method)
        info = {"kind": name, "true": np.asarray(truth.params[key], float).tolist(),
                "white": np.broadcast_to(np.asarray(truth.noise[f"{sensor}_white"], float),
                                         (3,)).tolist(),
                "span": float(rec.time[-1] - rec.time[0]), "fs": float(plan.sample_rate)}
        return (case, seed, np.zeros(0), gap,
                np.asarray(vals) / np.asarray(truth.params[key]), time.process_time() - t0, dof,
                info)
    z = []
    for sp in C.effect_of(method, name, sensor).specs(layout):
        est = np.asarray(res.params[sp.key], float)
        sig = np.asarray(res.sigma[sp.key], float)
        true = np.asarray(truth.params[sp.key], float)
        if sp.key == "lever_arm":  # the axial convention s . a = 0
            true = true - (true * axes).sum(axis=1)[:, None] * axes
        ok = np.isfinite(sig) & (sig > 0)
        z.append(((est - true)[ok] / sig[ok]).ravel())
    return case, seed, np.concatenate(z), gap, None, time.process_time() - t0, dof


def gap_bound(dof) -> float:
    """The residual / floor a seed may leave: 1.05, or for a fit of few equations (the
    gyro method: ~60 degrees of freedom, where sqrt(chi^2 / dof) scatters by ~9 %)
    the chi^2_dof 99 % point, sqrt(chi2.isf(0.01, dof) / dof)."""
    if dof is None:
        return 1.05
    from scipy import stats

    return max(1.05, float(np.sqrt(stats.chi2.isf(0.01, dof) / dof)))

def fit_with_rows(cases, n_of, workers: int = 1, seed0: int = 3000) -> dict:
    """{case: row} over n_of(case) seeds each (seed0 + 11 k), (case, seed) jobs on
    ``workers`` processes; CPU seconds summed over the seeds."""
    jobs = [(c, seed0 + 11 * k) for c in cases for k in range(n_of(c))]
    order = sorted(jobs, key=lambda j: -_cost((j[0], 0, None)))
    if workers > 1:
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(workers) as ex:
            out = list(ex.map(fit_with_z, order))
    else:
        out = [fit_with_z(j) for j in order]
    rows = {}
    for case in cases:
        got = sorted((o for o in out if o[0] == case), key=lambda o: o[1])
        z = np.concatenate([o[2] for o in got])
        gaps = np.array([o[3] for o in got])
        bounds = np.array([gap_bound(o[6]) for o in got])
        method, name, sensor, _ = C.CASES[case]
        from calib_cli.methods.fit_with import with_arg

        row = {"case": case, "with": f"fit {method} --with {with_arg(name, sensor)}",
               "n": len(got), "gap_ok": float(np.mean(gaps <= bounds)),
               "gap_bound": float(np.max(bounds)), "chi2_dof_mean": float(np.mean(gaps ** 2)),
               "gap_max": float(np.max(gaps)), "seconds": float(sum(o[5] for o in got))}
        if len(z):
            row["rms_z"] = float(np.sqrt(np.mean(z ** 2)))
            row["frac_33"] = float(np.mean(np.abs(z) < 3.3))
            row["entries"] = int(len(z))
        ratios = [o[4] for o in got if o[4] is not None]
        if ratios:
            r = np.concatenate(ratios)
            row["ratio_median"] = float(np.median(r))
            row["ratio_range"] = [float(r.min()), float(r.max())]
            # per seed: fitted / true per channel and the truth the Allan bounds need
            row["wander_seeds"] = [dict(o[7], ratio=np.asarray(o[4], float).tolist())
                                   for o in got]
        rows[case] = row
    return rows


def fit_with_table(rows) -> str:
    """The fit --with rows; a noise term's figure against its Allan bounds where the
    row has them (``allan_within``: the share of channels within the 95 % interval,
    ``allan_ci``: the interval's range over the seeds, ``allan_tau``: the averaging times)."""
    lines = ["| case | command | seeds | entries | RMS z | |z| < 3.3 | residual within bound "
             "| max residual / floor (bound) | mean (residual / floor)^2 "
             "| fitted / true (noise terms) | within the Allan 95 % interval (interval; tau) "
             "| CPU s |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        rz = f"{r['rms_z']:.3f}" if "rms_z" in r else "-"
        fz = f"{100 * r['frac_33']:.1f} %" if "frac_33" in r else "-"
        rt = (f"median {r['ratio_median']:.2f} ({r['ratio_range'][0]:.2f}-"
              f"{r['ratio_range'][1]:.2f})" if "ratio_median" in r else "-")
        al = "-"
        if "allan_within" in r:
            (l0, l1), (h0, h1), (t0, t1) = r["allan_ci"], r["allan_ci_hi"], r["allan_tau"]
            al = (f"{100 * r['allan_within']:.1f} % of {r['allan_n']} channels "
                  f"([{l0:.2f}-{l1:.2f}, {h0:.2f}-{h1:.2f}]; {t0:.0f}-{t1:.0f} s)")
        lines.append(f"| {r['case']} | `{r['with']}` | {r['n']} | {r.get('entries', '-')} | "
                     f"{rz} | {fz} | {100 * r['gap_ok']:.0f} % | {r['gap_max']:.3f} "
                     f"({r['gap_bound']:.2f}) | {r['chi2_dof_mean']:.3f} | {rt} | {al} | "
                     f"{r['seconds']:.0f} |")
    return "\n".join(lines)
