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
@click.option("--probe", "probe_port", metavar="PORT",
              help="Only find which known IMU protocol the unit on this serial port speaks "
              "(listens first, then sends each profile's identification request).")
def profiles_cmd(kind, show_all, as_json, probe_port):
    """List the shipped and user profiles with their one-line descriptions.

    A NAME is looked up in each directory of $CALIB_PROFILE_PATH (separated by
    ':'), then ~/.config/calib/profiles, then the shipped profiles; each holds
    imu/, turntable/, rimu/ and chamber/ subdirectories of NAME.toml. The first match
    wins; a path (with '/' or ending in .toml) is used as it is."""
    from rich.table import Table

    from calib_cli.cli.common import out_console, print_json
    from calib_cli.io.profiles import KINDS, all_profiles, profile_dirs

    if probe_port:
        return _probe(probe_port, as_json)

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


def _probe(port: str, as_json: bool) -> int:
    """``--probe PORT``: the protocols found, one a line (exit 3: none)."""
    from calib_cli.acquire.probe import candidate_profiles, no_protocol_message, probe_port
    from calib_cli.cli.common import out_console, print_json
    from calib_cli.errors import InputError

    profiles = candidate_profiles()
    found = probe_port(port, profiles)
    if as_json:
        print_json([{"profile": f.name, "how": f.how, "detail": f.detail} for f in found])
    if not found:
        raise InputError(no_protocol_message(port, profiles), port)
    if not as_json:
        for f in found:
            out_console.print(f"{f.name}: {f.detail} ({f.how})", markup=False, soft_wrap=True)
    return 0
