"""calib profiles [--kind imu|turntable|rimu|chamber] [--all] [--json]: the device and
geometry profiles that `--imu NAME`, `--table NAME`, `--chamber NAME` and `[rimu] profile = NAME`
find, in search order ($CALIB_PROFILE_PATH, ~/.config/calib/profiles, shipped)."""

from __future__ import annotations

import click

from calib_cli.cli.main import cli

COMPLETE_COMMAND = True


@cli.command("profiles")
@click.option("--kind", type=click.Choice(["imu", "turntable", "rimu", "chamber"]),
              help="Only this kind of profile.")
@click.option("--all", "show_all", is_flag=True,
              help="Also list profiles hidden by one of the same name earlier in the path.")
@click.option("--json", "as_json", is_flag=True, help="A JSON list on stdout.")
def profiles_cmd(kind, show_all, as_json):
    """List the shipped and user profiles with their one-line descriptions.

    A NAME is looked up in each directory of $CALIB_PROFILE_PATH (separated by
    ':'), then ~/.config/calib/profiles, then the shipped profiles; each holds
    imu/, turntable/, rimu/ and chamber/ subdirectories of NAME.toml. The first match
    wins; a path (with '/' or ending in .toml) is used as it is."""
    from rich.table import Table

    from calib_cli.cli.common import out_console, print_json
    from calib_cli.io.profiles import KINDS, all_profiles, profile_dirs

    rows = [p for p in all_profiles((kind,) if kind else KINDS)
            if show_all or not p["shadowed"]]
    if as_json:
        print_json(rows)
        return 0
    tab = Table(title="profiles (search order: " + ", ".join(
        f"{s} {d}" for s, d in profile_dirs()) + ")", title_justify="left")
    for c in ("kind", "name", "source", "description"):
        tab.add_column(c, overflow="fold")
    for p in rows:
        tab.add_row(p["kind"], p["name"] + (" (hidden)" if p["shadowed"] else ""),
                    p["source"], p["description"])
    out_console.print(tab)
    return 0
