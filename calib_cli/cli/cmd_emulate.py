"""calib emulate --imu PROFILE [--table PROFILE] [--chamber PROFILE] [--truth TRUTH.toml]
[--rate HZ] with fault injection (docs/acquisition.md)."""

from __future__ import annotations

import json
import signal
import sys

import click
import numpy as np

from calib_cli.cli.common import complete_profile, info, to_jsonable
from calib_cli.cli.main import cli

COMPLETE_COMMAND = True  # every subcommand lives here: loaded alone (cli/main.py)


@cli.command("emulate")
@click.option("--imu", "imu", required=True, shell_complete=complete_profile("imu"),
              help="IMU profile: a .toml path or a profile name (`calib profiles`).")
@click.option("--table", "table", shell_complete=complete_profile("turntable"),
              help="Turntable profile of the virtual table.")
@click.option("--truth", "truth_path", type=click.Path(dir_okay=False),
              help="Truth model TOML (docs/simulate.md); default: a random unit (--seed).")
@click.option("--plan", "plan_path", type=click.Path(dir_okay=False),
              help="Take the site (and a redundant unit's geometry) from this plan.")
@click.option("--rate", type=float, help="Output rate, Hz (default: the profile's).")
@click.option("--seed", default=0, show_default=True, type=int)
@click.option("--duration", type=float, help="Stop after S seconds (default: Ctrl-C).")
@click.option("--attitude-deg", nargs=3, type=float, default=(0.0, 0.0, 0.0),
              help="Initial attitude: roll pitch yaw.")
@click.option("--speed-dps", type=float, help="Slew speed of the virtual table.")
@click.option("--corrupt", default=0.0, type=click.FloatRange(0, 1),
              help="Fraction of frames with a bad byte.")
@click.option("--corrupt-where", type=click.Choice(["payload", "anywhere"]), default="payload",
              show_default=True, help="payload: payload/checksum bytes; anywhere: any byte.")
@click.option("--drop", default=0.0, type=click.FloatRange(0, 1), help="Fraction of frames dropped.")
@click.option("--garbage", default=0.0, type=click.FloatRange(0, 1),
              help="Fraction of frames preceded by a burst of random bytes.")
@click.option("--disconnect-at", type=float, help="Close the port S seconds after start ...")
@click.option("--disconnect-for", default=1.0, show_default=True, type=float,
              help="... for this long, then reopen it at the same path.")
@click.option("--fault-seed", default=1, show_default=True, type=int)
@click.option("--link-dir", type=click.Path(file_okay=False),
              help="Directory for the port symlinks (default: a new temporary one).")
@click.option("--can-interface", default="virtual", show_default=True,
              help="python-can interface for CAN profiles (virtual: this process only).")
@click.option("--can-channel", help="CAN channel name.")
@click.option("--truth-out", type=click.Path(dir_okay=False),
              help="Write the truth parameters as JSON here.")
@click.option("--chamber", "chamber", shell_complete=complete_profile("chamber"),
              help="Climatic chamber profile of a virtual chamber (SCPI or Modbus RTU) whose "
              "temperature the unit follows (docs/thermal.md).")
@click.option("--chamber-tau", default=300.0, show_default=True,
              type=click.FloatRange(0, min_open=True),
              help="The unit's first-order thermal time constant to the chamber air, s.")
@click.option("--chamber-ramp-dpm", type=click.FloatRange(0, min_open=True),
              help="The virtual chamber's ramp-rate limit, degC/min (default: the profile's).")
@click.option("--temp-start", default=25.0, show_default=True, type=float,
              help="Temperature of the unit (and chamber) at the start, degC.")
@click.option("--datagram", metavar="ID",
              help="Profiles with [[datagram]] entries: the identifier (hex, e.g. A5) of the "
              "datagram to send (default: the first).")
def emulate_cmd(imu, table, truth_path, plan_path, rate, seed, duration, attitude_deg, speed_dps,
                corrupt, corrupt_where, drop, garbage, disconnect_at, disconnect_for, fault_seed,
                link_dir, can_interface, can_channel, truth_out, chamber, chamber_tau,
                chamber_ramp_dpm, temp_start, datagram):
    """Emulate an IMU (and a turntable, a climatic chamber) on pseudo-terminals or a
    virtual CAN bus.

    Prints one JSON line with the port paths on stdout, streams until Ctrl-C
    or --duration, then prints one JSON line with the injected faults."""
    import dataclasses

    from calib_cli.acquire.emulator import Emulator, Faults
    from calib_cli.acquire.profile import load_imu_profile, load_table_profile
    from calib_cli.errors import InputError
    from calib_cli.io.plan import load_plan
    from calib_cli.io.truth import load_truth
    from calib_cli.model.earth import Site
    from calib_cli.model.effects import Layout
    from calib_cli.plan import plan_layout

    prof = load_imu_profile(imu)
    if link_dir:  # the documented example names a directory that does not exist yet
        import os

        from calib_cli.errors import OutputError

        try:
            os.makedirs(link_dir, exist_ok=True)
        except OSError as exc:
            raise OutputError(f"cannot create the link directory: {exc.strerror}",
                              link_dir) from None
    tprof = load_table_profile(table) if table else None
    if tprof is not None and speed_dps:
        tprof = dataclasses.replace(tprof, speed_dps=speed_dps)
    plan = load_plan(plan_path) if plan_path else None
    site = plan.site if plan else Site()
    if prof.redundant:
        if plan is None or plan.kind != "rimu":
            raise InputError("a redundant-unit profile needs --plan with a [rimu] geometry",
                             prof.path)
        layout = plan_layout(plan)
        if layout.n != prof.n_sensors:
            raise InputError(f"the plan's [rimu] has {layout.n} sensors, the profile "
                             f"{prof.n_sensors}", plan_path)
    else:
        layout = Layout()
    truth = load_truth(truth_path, layout) if truth_path else None
    cprof = None
    if chamber:
        from calib_cli.acquire.chamber import load_chamber_profile

        cprof = load_chamber_profile(chamber)
        if cprof.kind == "manual":
            raise click.UsageError("--chamber: a manual chamber has nothing to emulate")
        if chamber_ramp_dpm:
            cprof = dataclasses.replace(cprof, max_ramp_dpm=chamber_ramp_dpm)
        if truth is None and not prof.redundant:  # a unit with temperature drift
            from calib_cli.sim.thermal_unit import thermal_truth

            truth = thermal_truth(np.random.default_rng(seed))
    dg = 0
    if datagram is not None:
        ids = [lay.name for lay in prof.layouts] if prof.format == "binary" else []
        if datagram.upper() not in ids or len(ids) < 2:
            raise click.UsageError(f"--datagram: profile {prof.name!r} has "
                                   f"{'datagrams ' + ', '.join(ids) if len(ids) > 1 else 'no datagrams'}")
        dg = ids.index(datagram.upper())
    faults = Faults(corrupt=corrupt, corrupt_where=corrupt_where, drop=drop, garbage=garbage,
                    disconnect_at=disconnect_at, disconnect_for=disconnect_for, seed=fault_seed)
    em = Emulator(prof, tprof, truth=truth, site=site, rate=rate, faults=faults, seed=seed,
                  layout=layout, attitude_deg=attitude_deg, link_dir=link_dir,
                  can_interface=can_interface, can_channel=can_channel, chamber=cprof,
                  chamber_tau=chamber_tau, temp_c=temp_start, datagram=dg)
    if truth_out:
        with open(truth_out, "w") as fh:
            json.dump(to_jsonable({k: np.asarray(v) for k, v in em.truth.params.items()}), fh)
    sys.stdout.write(json.dumps(em.paths) + "\n")
    sys.stdout.flush()
    info(f"emulating {prof.name} at {em.fs:g} Hz: " + ", ".join(f"{k} {v}"
                                                                  for k, v in em.paths.items()))
    old = signal.signal(signal.SIGTERM, lambda *_: em._stop.set())
    try:
        em.run(duration)
    except KeyboardInterrupt:
        pass
    finally:
        signal.signal(signal.SIGTERM, old)
        em.stop()
    inj = em.injected
    summary = {"frames": inj.frames, "samples": inj.samples, "corrupted": inj.corrupted,
               "dropped": inj.dropped, "garbage_bursts": inj.garbage_bursts,
               "disconnect_frames": inj.disconnect_frames, "overflow": inj.overflow}
    if em.responder is not None:  # the configuration exchange (acquire/device.py)
        summary["commands"] = len(em.responder.log)
        summary["rate_requests_hz"] = sorted(set(em.responder.rate_requests))
    sys.stdout.write(json.dumps(summary) + "\n")
    sys.stdout.flush()
    info("emulator stopped: " + ", ".join(f"{k} {v}" for k, v in summary.items()))
