"""calib recover JOURNAL --out RAW.h5: a raw file from a recorder's journal
(after a crash, SIGKILL or power loss: everything up to the last flush)."""

from __future__ import annotations

import click

from calib_cli.cli.common import info, json_output_option, output_json
from calib_cli.cli.main import cli

COMPLETE_COMMAND = True  # every subcommand lives here: loaded alone (cli/main.py)


@cli.command("recover")
@click.argument("journal", type=click.Path(dir_okay=False))
@click.option("--out", required=True, type=click.Path(dir_okay=False))
@json_output_option
def recover_cmd(journal, out, as_json=False):
    """Turn a recording journal into raw.h5."""
    from calib_cli.acquire.session import journal_to_recording
    from calib_cli.io.h5 import write_raw

    rec = journal_to_recording(journal)
    write_raw(out, rec, [journal])
    c = rec.counters
    state = ("complete (the recorder closed it)" if c.get("journal_complete") else
             "not closed by its recorder (cut short: killed, crashed or power lost)")
    skipped = c.get("journal_records_skipped", 0)
    if skipped:
        state += (f"; {skipped} damaged record{'s' * (skipped > 1)} skipped "
                  f"({c.get('journal_bytes_skipped', 0)} bytes)")
    if c.get("journal_rows_dropped"):
        state += f"; {c['journal_rows_dropped']} rows with non-finite values or time going back dropped"
    info(f"recovered {len(rec)} samples, {len(rec.segments)} segments from a journal "
         f"{state} -> {out}")
    if as_json:
        output_json(out, "raw")
