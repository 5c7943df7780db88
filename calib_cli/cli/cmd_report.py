"""calib report CAL.h5 [RAW.h5|ALLAN.h5] --out DIR"""

from __future__ import annotations

from pathlib import Path

import click

from calib_cli.cli.common import info
from calib_cli.cli.main import cli
from calib_cli.errors import CalibError, DamagedInput, InputError
from calib_cli.io.h5 import file_kind, provenance, read_calibration

COMPLETE_COMMAND = True  # every subcommand lives here: loaded alone (cli/main.py)

MIN_ALLAN_S = 60.0  # a record shorter than this is not a free-running noise record


def _allan_for(raw: str, kind: str):
    """(AllanResult or None, note)."""
    if kind == "allan":
        from calib_cli.io.allan_h5 import read_allan

        return read_allan(raw), None
    from calib_cli.cli.cmd_allan import compute_allan

    try:
        res = compute_allan(raw, hint="`calib allan RAW --segment LABEL --out ALLAN.h5`, then "
                            "`calib report CAL ALLAN.h5`")
    except DamagedInput:
        raise  # damaged samples are exit 3, not a note in a report (issue 15)
    except CalibError as exc:
        return None, f"No Allan deviation of {Path(raw).name}: {exc.message}"
    if res.duration < MIN_ALLAN_S:
        return None, (f"{Path(raw).name} is not a free-running record (longest span "
                      f"{res.duration:.3g} s < {MIN_ALLAN_S:.0f} s): no Allan plot.")
    return res, None


@cli.command("report")
@click.argument("cal", type=click.Path(dir_okay=False))
@click.argument("raw", required=False, type=click.Path(dir_okay=False))
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False),
              help="Directory for report.md, report.html, the PNG figures (created).")
@click.option("--tolerances", "tol_path", type=click.Path(dir_okay=False),
              help="Tolerance file (as for `calib batch`): the verdict checks the parameters "
                   "against it instead of against the noise floor.")
@click.option("--history", "history_dir", type=click.Path(file_okay=False),
              help="The directory of the unit's earlier calibrations (a `calib batch` output "
                   "directory): the tolerances' max_change_sigma compares with the last of "
                   "them, as the batch does. Without it that rule is not evaluated and the "
                   "verdict says so.")
@click.option("--pdf", "pdf", is_flag=True,
              help="Also write the same report as report.pdf (A4, matplotlib).")
@click.option("--json", "as_json", is_flag=True,
              help='Print {"output", "kind", "html", "markdown", "pdf", "verdict", "figures"} '
                   "as JSON on stdout and nothing else there.")
def report_cmd(cal, raw, out_dir, tol_path, history_dir=None, pdf=False, as_json=False):
    """Markdown and self-contained HTML report of a calibration, with plots.

    RAW (optional): a free-running raw record (or an 'allan' file) adds the
    Allan deviation; method sections may also use it (docs/report.md)."""
    from calib_cli.report.builder import ReportContext, build_report, write_report

    c = read_calibration(cal)
    ctx = ReportContext(cal=c, cal_path=cal, prov=provenance(cal))
    if file_kind(cal) == "diagnosis":  # its steps and residuals: a section of their own
        from calib_cli.io.diag_h5 import read_diagnosis, read_diagnosis_arrays

        ctx.diagnosis = {"summary": read_diagnosis(cal), "arrays": read_diagnosis_arrays(cal)}
    if tol_path:
        from calib_cli.io.tolerance import load_tolerances

        ctx.tolerances, ctx.tolerances_path = load_tolerances(tol_path), tol_path
    if history_dir:
        if not tol_path:
            raise click.UsageError("--history applies to --tolerances")
        from calib_cli.io.history import scan

        ctx.history = scan(history_dir, ctx.prov.get("unit_serial") or c.serial or "")
    if raw:
        kind = file_kind(raw)
        if kind not in ("raw", "corrected", "allan"):
            raise InputError(f"a {kind!r} file; expected a raw, corrected or allan file", raw)
        ctx.raw_path, ctx.raw_kind = raw, kind
        ctx.allan, note = _allan_for(raw, kind)
        if note:
            ctx.notes.append(note)
    sections = build_report(ctx)
    title = f"Calibration report: {c.serial or 'unit'} ({c.method}), {Path(cal).name}"
    out = Path(out_dir)
    # built in a temporary directory beside it that then replaces it whole: no
    # partial report, and no figure of an older report survives
    from calib_cli.io.outpath import atomic_dir

    with atomic_dir(out) as tmp:
        manifest = write_report(sections, title, Path(tmp))
        if pdf:
            from calib_cli.report.pdf import write_pdf

            pages = write_pdf(sections, title, Path(tmp) / "report.pdf")
    n = len(manifest["figures"])
    info(f"report with {n} figure{'' if n == 1 else 's'} -> {out / 'report.html'}")
    if pdf:
        info(f"{pages} pages -> {out / 'report.pdf'}")
    if as_json:
        from calib_cli.cli.common import print_json
        from calib_cli.report.builder import verdict

        word, line = verdict(ctx)
        print_json({"output": str(out), "kind": "report", "html": str(out / "report.html"),
                    "markdown": str(out / "report.md"),
                    "pdf": str(out / "report.pdf") if pdf else None,
                    "verdict": {"result": word, "line": line},
                    "figures": [{"file": str(out / f["file"]), "caption": f["caption"]}
                                for f in manifest["figures"]],
                    "sections": [s.title for s in sections]})
    return 0
