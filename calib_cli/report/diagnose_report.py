"""`calib diagnose --report DIR`: PNG plots and a Markdown summary.

- disagreement.png: the base model's residuals (and the final model's) by
  time, by segment, by table rate, by temperature and by tilt.
- step<k>_<effect>.png: the residuals of the channel the effect moves most,
  before and after adding it, against the effect's physical signature
  (rate^2, specific force, f^2, temperature, rate change) and against the
  fitted signature itself (the effect's contribution, noise units: points
  on the 1:1 line before, flat after).
- summary.md: the steps, scores and thresholds, gaps, untested effects.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from calib_cli.io.escape import md_text, mpl_text
from calib_cli.methods.diagnose import WANDERS, Diagnosis
from calib_cli.methods.diagnose_candidates import effect_key
from calib_cli.methods.diagnose_fit import predict_bins
from calib_cli.methods.diagnose_problem import BIN_S

AX = "xyz"


def _channels(pb):
    out = []
    for s in pb.sensors:
        n = pb.y[s].shape[1]
        out += [(s, i, f"{s} {AX[i] if n == 3 else i}") for i in range(n)]
    return out


def effect_contribution(d: Diagnosis, k: int) -> dict:
    """sensor -> (M, n): what step k's effect adds to the prediction, noise units."""
    pb = d.problem
    f = d.fits[k + 1]
    st = d.steps[k]
    p0 = dict(f.params)
    if st.effect in WANDERS:  # a wandering bias is in the noise model, not the prediction
        return {s: np.zeros_like(pb.ymean[s]) for s in pb.sensors}
    neutral = f.spec.model.neutral_params()
    for key in st.params:
        p0[key] = neutral[key]
    a = predict_bins(pb, f.spec, f.params, f.mount)
    b = predict_bins(pb, f.spec, p0, f.mount)
    return {s: (a[s] - b[s]) / pb.whitener(s) for s in pb.sensors}


def physical_signature(d: Diagnosis, k: int, sensor: str, ch: int):
    """(x values per bin, axis label) of step k's effect for one channel."""
    pb = d.problem
    st = d.steps[k]
    name = st.effect
    if name in ("lever_arm", "proof_mass_offsets"):
        return pb.bin_mean((pb.kin.w ** 2).sum(axis=1)), "table rate^2, (rad/s)^2"
    if name == "time_offset":
        w = pb.kin.w
        n = np.linalg.norm(w, axis=1)
        rc = (pb.kin.dw * w).sum(axis=1) / np.where(n > 0, n, 1.0)
        return pb.bin_mean(rc), "rate change along the rate, rad/s^2"
    if name == "temperature_drift" and pb.kin.temp is not None:
        return pb.temp(), "temperature, degC"
    if name == "g_sensitivity":
        D = np.abs(np.asarray(st.params["gyro_D"]))
        j = int(np.argmax(D[ch]))
        return pb.bin_mean(pb.kin.f[:, j]), f"specific force along {AX[j]}, m/s^2"
    if name in ("accel_nonlinearity", "scale_asymmetry"):
        src = pb.kin.f if sensor == "accel" else pb.kin.w
        u = "m/s^2" if sensor == "accel" else "rad/s"
        return pb.bin_mean(src[:, ch]), f"input along {AX[ch]}, {u}"
    if name == "misalignment":
        M = np.abs(np.asarray(st.params[f"{sensor}_misalignment"]))
        j = int(np.argmax(M[ch]))
        src = pb.kin.f if sensor == "accel" else pb.kin.w
        return pb.bin_mean(src[:, j]), f"input along {AX[j]}"
    return pb.bin_t, "time, s"


def _disagreement(d: Diagnosis, path: Path):
    import matplotlib.pyplot as plt

    from calib_cli.report.figures import use_palette

    use_palette()  # the Okabe-Ito colour-blind-safe cycle of every calib figure
    pb = d.problem
    stages = [("base model", d.fits[0])] + ([("final model", d.fits[-1])] if d.steps else [])
    rate = np.degrees(np.sqrt(pb.bin_mean((pb.kin.w ** 2).sum(axis=1))))
    tilt = np.degrees(np.arccos(np.clip(pb.bin_mean(pb.kin.f[:, 2]) / pb.g, -1, 1)))
    temp = pb.temp()
    xs = [("time, s", pb.bin_t), ("segment", pb.bin_seg.astype(float))]
    if np.nanmax(rate, initial=0.0) > 1.0:  # a static record has no rate to plot against
        xs.append(("rate, deg/s", rate))
    xs.append(("tilt of z from up, deg", tilt))
    if temp is not None and np.ptp(temp) > 0.5:
        xs.append(("temperature, degC", temp))
    fig, axes = plt.subplots(len(xs), 1, figsize=(9, 2.3 * len(xs)))
    for ax, (lab, x) in zip(np.atleast_1d(axes), xs):
        for name, f in stages:
            res = f.residual_blocks(pb)
            z = np.sqrt(np.mean(np.concatenate([res[s] for s in pb.sensors], axis=1) ** 2,
                                axis=1))
            ax.plot(x, z, ".", ms=3, label=name, alpha=0.7)
        ax.axhline(1.0, color="k", lw=0.8, ls="--")
        ax.set_xlabel(lab)
        if lab == "segment":  # the plan's labels, not raw indices
            segs = np.unique(pb.bin_seg)
            names = [str(pb.seg_labels[int(i)]) if 0 <= int(i) < len(pb.seg_labels)
                     else str(int(i)) for i in segs]
            ax.set_xticks(segs.astype(float), [mpl_text(n) for n in names], rotation=45,
                          ha="right", fontsize=7)
        ax.set_ylabel("RMS resid. / noise")
    np.atleast_1d(axes)[0].legend(loc="upper right")
    np.atleast_1d(axes)[0].set_title("Where the model and the data disagree (bin RMS over "
                                     "channels, noise units; 1 = noise)")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _step_plot(d: Diagnosis, k: int, path: Path):
    import matplotlib.pyplot as plt

    from calib_cli.report.figures import use_palette

    use_palette()
    pb = d.problem
    contrib = effect_contribution(d, k)
    res0, res1 = d.fits[k].residual_blocks(pb), d.fits[k + 1].residual_blocks(pb)
    stochastic = d.steps[k].effect in WANDERS
    best, bs, bi = -np.inf, None, 0
    for s, i, _ in _channels(pb):
        if stochastic:  # the channel whose residuals the wander whitens most
            v = float(np.mean(res0[s][:, i] ** 2) - np.mean(res1[s][:, i] ** 2))
        else:
            v = float(np.sqrt(np.mean(contrib[s][:, i] ** 2)))
        if v > best:
            best, bs, bi = v, s, i
    before = res0[bs][:, bi]
    after = res1[bs][:, bi]
    x, xl = physical_signature(d, k, bs, bi)
    st = d.steps[k]
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4))
    a1.plot(x, before, ".", ms=3, label="before")
    a1.plot(x, after, ".", ms=3, label="after")
    a1.set_xlabel(xl)
    a1.set_ylabel(f"{bs} {AX[bi] if pb.y[bs].shape[1] == 3 else bi} residual / noise")
    a1.legend()
    if stochastic:  # a wander's signature: residuals correlated over time, white after
        lags = np.arange(1, min(40, len(before) // 4))
        for lab, r in (("before", before), ("after", after)):
            r = r - r.mean()
            ac = [float(r[:-m] @ r[m:] / (r @ r)) for m in lags]
            a2.plot(lags * BIN_S, ac, ".-", ms=3, label=lab)
        a2.axhline(0.0, color="k", lw=0.8)
        a2.set_xlabel("lag, s")
        a2.set_ylabel("autocorrelation of the residual")
    else:
        sig = contrib[bs][:, bi]
        a2.plot(sig, before, ".", ms=3, label="before")
        a2.plot(sig, after, ".", ms=3, label="after")
        lim = [float(np.min(sig)), float(np.max(sig))]
        a2.plot(lim, lim, "k-", lw=0.8, label="1:1")
        a2.set_xlabel("fitted signature of the effect, noise units")
    a2.legend()
    fig.suptitle(f"step {k + 1}: {effect_key(st.effect, st.sensor)}"
                 + f" (score {st.score:.1f}, threshold {st.threshold:.1f}; RMS "
                 f"{st.residual_rms_before:.2f} -> {st.residual_rms_after:.2f})")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def write_report(d: Diagnosis, out_dir, source: str = "") -> list[str]:
    """Write the PNGs and summary.md; returns the file names."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files = ["disagreement.png"]
    _disagreement(d, out / "disagreement.png")
    for k, st in enumerate(d.steps):
        name = f"step{k + 1}_{(st.sensor + '_' if st.sensor else '')}{st.effect}.png"
        _step_plot(d, k, out / name)
        files.append(name)
    j = d.to_json()
    lines = [f"# calib diagnose: {md_text(source or 'recording')} ({md_text(d.method)})", "",
             f"Base model: {', '.join(d.base_model)}.", "",
             f"Noise floor (RMS white noise would leave after the final fit): "
             f"{d.noise_rms:.3f} noise units. Residual RMS: {d.residual_rms_initial:.3f} with "
             f"the base model, {d.residual_rms_final:.3f} at the end "
             f"({j['gap_left']:.2f}x the floor).", "",
             "![disagreement](disagreement.png)", ""]
    if not d.steps:
        lines += ["No candidate effect passed its threshold: the base model explains the "
                  "data down to the noise.", ""]
    for k, st in enumerate(d.steps):
        lines += [f"## Step {k + 1}: {effect_key(st.effect, st.sensor)}", "",
                  st.evidence + ".", "",
                  f"![step {k + 1}]({files[k + 1]})", ""]
    lines += ["## Candidates per round", ""]
    for i, rnd in enumerate(d.rounds):
        lines += [f"Round {i + 1}:", "",
                  "| candidate | score | threshold | dof | p | within-segment score |",
                  "|---|---|---|---|---|---|"]
        lines += [f"| {r['candidate']} | {r['score']:.1f} | {r['threshold']:.1f} | {r['dof']} "
                  f"| {r['p_value']:.2g} | "
                  + (f"{r['within_segment_score']:.1f}" if "within_segment_score" in r else "")
                  + " |" for r in rnd]
        lines.append("")
    if d.untested:
        lines += ["## Not tested", ""] + [f"- {md_text(k)}: {md_text(v)}"
                                          for k, v in d.untested.items()] + [""]
    if d.notes:
        lines += ["## Notes", ""] + [f"- {md_text(n)}" for n in d.notes] + [""]
    lines += calibration_section(d, source)
    (out / "summary.md").write_text("\n".join(lines), encoding="utf-8")
    return files + ["summary.md"]


def calibration_section(d: Diagnosis, source: str = "") -> list[str]:
    """The report's last section: the command that writes the final model's calibration
    and the before/after of the quantity the user cares about (|g| error per static
    position for accelerometer triads, the residual per segment (rotating cycles) in
    noise units for every method)."""
    from calib_cli.methods.with_effects import g_error_per_position

    lines = ["## The calibration", ""]
    cmd = d.fit_command(source or "RAW.h5", "CAL.h5")
    if cmd:
        lines += ["The calibration of the final model (DIAG.h5 holds it too; `calib diagnose "
                  "--calibration CAL.h5` writes it as well):", "", f"    {md_text(cmd)}", ""]
    else:
        lines += ["No effect was added: the base model is the calibration (`calib fit "
                  f"{md_text(d.method)}`).", ""]
    pb = d.problem
    base, final = d.fits[0], d.fits[-1]
    g0 = g_error_per_position(pb, base.spec.model, base.params)
    g1 = g_error_per_position(pb, final.spec.model, final.params)
    counts = pb.units.get("accel") == "count"
    if g0 and not counts:
        mg = 1e3 / 9.80665
        lines += ["|g| error per static position (mg), base model -> final model:", "",
                  "| position | base | final |", "|---|---|---|"]
        lines += [f"| {md_text(a[0])} | {a[2] * mg:.4f} | {b[2] * mg:.4f} |"
                  for a, b in zip(g0, g1)]
        r0 = float(np.sqrt(np.mean([a[2] ** 2 for a in g0])))
        r1 = float(np.sqrt(np.mean([b[2] ** 2 for b in g1])))
        lines += ["", f"RMS {r0 * mg:.4f} mg -> {r1 * mg:.4f} mg.", ""]
    rows = d.by_segment()
    lines += ["Residual RMS per segment (noise units; rotating segments are the cycles), base "
              "model -> final model:", "", "| segment | kind | base | final |",
              "|---|---|---|---|"]
    lines += [f"| {md_text(r['segment'])} | {md_text(r['kind'])} | {r['rms_initial']:.2f} | "
              f"{r['rms_final']:.2f} |" for r in rows]
    return lines + [""]


def write_gyro_report(d, out_dir, source: str = "") -> list[str]:
    """summary.md of a diagnosis on a method's own equations (the gyro fit's,
    methods/diagnose_gyro.py; the turntable filter's, methods/turntable/diagnose.py): the
    steps, the candidates per round, and the calibration (the gyro fit's with the
    turn-angle errors before and after)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    j = d.to_json()
    lines = [f"# calib diagnose: {md_text(source or 'recording')} ({d.method})", "",
             f"Base model: {', '.join(md_text(x) for x in d.base_model)}.", "",
             f"Residual RMS (noise units): {d.residual_rms_initial:.3f} with the base model, "
             f"{d.residual_rms_final:.3f} at the end, noise floor {d.noise_rms:.3f} "
             f"({j['gap_left']:.2f}x).", ""]
    if not d.steps:
        lines += ["No candidate effect passed its threshold.", ""]
    for k, st in enumerate(d.steps):
        lines += [f"## Step {k + 1}: {md_text(st.with_arg)}", "", md_text(st.evidence) + ".", ""]
    lines += ["## Candidates per round", ""]
    for i, rnd in enumerate(d.rounds):
        lines += [f"Round {i + 1}:", "", "| candidate | score | threshold | dof | p |",
                  "|---|---|---|---|---|"]
        lines += [f"| {md_text(r['candidate'])} | {r['score']:.1f} | {r['threshold']:.1f} | "
                  f"{r['dof']} | {r['p_value']:.2g} |" for r in rnd]
        lines.append("")
    if d.untested:
        lines += ["## Not tested", ""] + [f"- {md_text(k)}: {md_text(v)}"
                                          for k, v in d.untested.items()] + [""]
    if d.notes:
        lines += ["## Notes", ""] + [f"- {md_text(n)}" for n in d.notes] + [""]
    lines += ["## The calibration", ""]
    cmd = d.fit_command(source or "RAW.h5", "CAL.h5")
    lines += ([f"    {md_text(cmd)}", ""] if cmd else
              [f"No effect was added: `calib fit {d.method}` is the calibration.", ""])
    te = j.get("turn_angle_error_deg")
    if te:
        lines += ["Turn-angle error (integrated angle minus the plan's, deg), base model -> "
                  "final model:", "", "| turn | base | final |", "|---|---|---|"]
        lines += [f"| {md_text(r['turn'])} | {r['error_initial_deg']:.4f} | "
                  f"{r['error_final_deg']:.4f} |" for r in te] + [""]
    tr = j.get("transition_residual_rms_deg") or [None, None]
    if tr[0] is not None:
        lines += [f"Transition residual RMS: {tr[0]:.4f} deg -> {tr[1]:.4f} deg.", ""]
    if "final_chi2" in j:
        lines += [f"Final model: chi^2 {j['final_chi2']:.0f} for {j['final_dof']:.0f} degrees of "
                  f"freedom (99 % point {j['final_chi2_99']:.0f}).", ""]
    files = ["summary.md"]
    if hasattr(d, "residual_series"):
        _series_plot(*d.residual_series(), out / "disagreement.png")
        lines += ["![disagreement](disagreement.png)", ""]
        files.append("disagreement.png")
        for k, st in enumerate(d.steps):  # each step: the model before it and after it
            name = f"step{k + 1}_{(st.sensor + '_' if st.sensor else '')}{st.effect}.png"
            _series_plot(*d.residual_series(k, k + 1), out / name)
            lines += [f"![step {k + 1}]({name})", ""]
            files.append(name)
    (out / "summary.md").write_text("\n".join(lines), encoding="utf-8")
    return files


def _series_plot(t, before, after, path) -> None:
    """The accelerometers' residuals over time (units of their white noise), base model
    and final model, one panel per axis."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, 1, figsize=(9, 6), sharex=True)
    for i, ax in enumerate(axes):
        ax.plot(t, before[:, i], ".", ms=1.5, color="tab:red", label="base model")
        ax.plot(t, after[:, i], ".", ms=1.5, color="tab:blue", label="final model")
        ax.set_ylabel(f"accel {'xyz'[i]} (sigma)")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper right", markerscale=6)
    axes[-1].set_xlabel("time (s)")
    fig.suptitle("Accelerometer residuals, block means in units of their white noise")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
