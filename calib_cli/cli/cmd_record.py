"""calib record --imu PROFILE --port PORT [--table PROFILE --table-port PORT]
[--chamber PROFILE --chamber-port PORT]
(--plan PLAN | --duration S) --out RAW.h5 (docs/acquisition.md)"""

from __future__ import annotations

import contextlib
import os
import signal
import time

import click
from rich.live import Live
from rich.table import Table

from calib_cli.cli.common import (
    Ctx,
    complete_profile,
    err_console,
    info,
    interactive,
    json_output_option,
    output_json,
)
from calib_cli.cli.main import cli
from calib_cli.errors import CalibError, InputError

COMPLETE_COMMAND = True  # every subcommand lives here: loaded alone (cli/main.py)


class LiveDisplay:
    """The live panel (rich) on a terminal; one line per segment otherwise."""

    def __init__(self, total: int):
        self.total = total
        self.live = None
        self.last = 0.0
        self.last_label = None
        if interactive():
            self.live = Live(console=err_console, auto_refresh=False, transient=False)
            self.live.start()

    def render(self, s) -> Table:
        c = s.counts()
        t = Table(show_header=False, box=None, title="calib record")
        t.add_row("segment", s.current_label or "-")
        t.add_row("state", s.state)
        bar = int(30 * s.progress)
        t.add_row("progress", "#" * bar + "." * (30 - bar) + f" {100 * s.progress:5.1f} %")
        t.add_row("sample rate", f"{s.rate_meas:8.1f} Hz (nominal {s.prof.rate_hz:g})")
        t.add_row("samples", str(s.n_rows))
        t.add_row("checksum errors", str(c["checksum_errors"]))
        t.add_row("dropped frames", f"{c['gaps']} (counter gaps)")
        t.add_row("garbage bytes", str(c["garbage_bytes"]))
        t.add_row("disconnects", str(c["disconnects"]))
        return t

    def __call__(self, s) -> None:
        if self.live is not None:
            now = time.monotonic()
            if now - self.last >= 0.25:
                self.last = now
                self.live.update(self.render(s), refresh=True)
        elif s.current_label and s.current_label != self.last_label:
            self.last_label = s.current_label
            info(f"segment {s.current_label}")

    @contextlib.contextmanager
    def paused(self):
        if self.live is not None:
            self.live.stop()
        try:
            yield
        finally:
            if self.live is not None:
                self.live.start()

    def close(self, session=None) -> None:
        if self.live is not None:
            if session is not None:  # the final state, not the last throttled frame
                session.state = "finished" if session.finished else "stopped"
                self.live.update(self.render(session), refresh=True)
            self.live.stop()
            self.live = None


def _raise_interrupt(*_):
    raise KeyboardInterrupt  # SIGTERM ends a recording like Ctrl-C


@cli.command("record")
@click.option("--imu", "imu", required=True, shell_complete=complete_profile("imu"),
              help="IMU profile: a .toml path, a profile name (`calib profiles`), or auto "
              "(find the protocol on --port).")
@click.option("--port", help="Serial port of the IMU (serial profiles).")
@click.option("--can-interface", help="python-can interface (default: the profile's).")
@click.option("--can-channel", help="CAN channel (default: the profile's).")
@click.option("--table", "table", shell_complete=complete_profile("turntable"),
              help="Turntable profile (path, shipped name, or 'manual').")
@click.option("--table-port", help="Serial port of the turntable.")
@click.option("--plan", "plan_path", type=click.Path(dir_okay=False), help="Experiment plan.")
@click.option("--duration", type=float, help="Free-running log of S seconds (no plan); "
              "without --plan and --duration: until Ctrl-C.")
@click.option("--rate", type=float, help="The device's output rate, Hz, when it is configured "
              "otherwise than the profile's rate_hz (time from the sequence counter uses it).")
@click.option("--out", required=True, type=click.Path(dir_okay=False), help="raw.h5 to write.")
@click.option("--journal", "journal_path", type=click.Path(dir_okay=False),
              help="Append-only journal (default: OUT.journal).")
@click.option("--keep-journal", is_flag=True, help="Keep the journal after a clean end.")
@click.option("--settle-window", default=0.5, show_default=True, type=float,
              help="Stillness window, s.")
@click.option("--accel-still", type=click.FloatRange(0, min_open=True),
              help="Stillness: max accel std, m/s^2 (default: 5x the profile's [noise] "
              "accel_std, else 5x the std measured in the first second; at least 0.05).")
@click.option("--gyro-still", type=click.FloatRange(0, min_open=True),
              help="Stillness: max gyro std, rad/s (default: 5x the profile's [noise] "
              "gyro_std, else 5x the std measured in the first second; at least 0.01).")
@click.option("--settle-timeout", default=120.0, show_default=True, type=float,
              help="Give up when the unit has not settled after S seconds.")
@click.option("--segment-duration", default=10.0, show_default=True, type=float,
              help="Duration of plan segments without duration_s, s.")
@click.option("--reconnect-timeout", default=30.0, show_default=True, type=float,
              help="How long to wait for a disconnected device, s.")
@click.option("--gravity-tolerance", default=10.0, show_default=True, type=click.FloatRange(0),
              help="Refuse a position whose measured gravity direction is further than this "
              "(deg) from the one its attitude_deg implies, and ask again (0: no check).")
@click.option("--no-data-timeout", default=3.0, show_default=True, type=click.FloatRange(0),
              help="Stop when no valid frame arrives within S seconds of the start.")
@click.option("--force", is_flag=True, help="Replace an existing recording at --out, and set "
              "an existing journal aside (renamed, never deleted).")
@click.option("--no-check", is_flag=True, help="Skip the plan check before recording.")
@click.option("--chamber", "chamber", shell_complete=complete_profile("chamber"),
              help="Climatic chamber profile (path, shipped name, or 'manual') for plans with "
              "chamber_temp_degC (docs/thermal.md).")
@click.option("--chamber-port", help="Serial port of the chamber.")
@json_output_option
def record_cmd(imu, port, can_interface, can_channel, table, table_port, plan_path, duration,
               rate, out, journal_path, keep_journal, settle_window, accel_still, gyro_still,
               settle_timeout, segment_duration, reconnect_timeout, gravity_tolerance,
               no_data_timeout, force, no_check, chamber, chamber_port, as_json=False):
    """Record an experiment plan (or a free-running log) from an IMU into raw.h5."""
    from calib_cli.acquire.profile import load_imu_profile
    from calib_cli.acquire.session import free_run_plan
    from calib_cli.io.plan import load_plan, parse_plan

    if plan_path and duration is not None:
        raise click.UsageError("give --plan or --duration, not both")
    if imu == "auto":  # probe the port for a known protocol (acquire/probe.py)
        if not port:
            raise click.UsageError("--imu auto needs --port")
        from calib_cli.acquire.probe import candidate_profiles, no_protocol_message, probe_port

        cands = candidate_profiles()
        found = probe_port(port, cands)
        if not found:
            raise InputError(no_protocol_message(port, cands), port)
        imu = found[0].name
        info(f"--imu auto: {imu} ({found[0].detail}, {found[0].how})")
    prof = load_imu_profile(imu)
    if rate:
        import dataclasses

        prof = dataclasses.replace(prof, rate_hz=float(rate))
    if prof.format != "can" and not port:
        raise click.UsageError(f"profile {prof.name!r} is a serial device: give --port")
    plan = load_plan(plan_path) if plan_path else parse_plan(free_run_plan(duration), "free-run")
    if plan_path and not no_check:  # issue 20: warn when the plan cannot deliver
        from calib_cli.design import record_warning

        warning = record_warning(plan, prof.rate_hz)
        if warning:
            err_console.print(f"calib: warning: {warning}", markup=False, soft_wrap=True)
    from calib_cli.acquire.chamber import check_plan, load_chamber_profile

    cprof = load_chamber_profile(chamber) if chamber else None
    if cprof is not None and cprof.kind != "manual" and not chamber_port:
        raise click.UsageError("a serial chamber needs --chamber-port")
    for w in check_plan(plan, cprof):  # setpoints within the chamber's range
        err_console.print(f"calib: warning: {w}", markup=False, soft_wrap=True)
    out_dir = os.path.dirname(os.path.abspath(out))
    if not os.path.isdir(out_dir):
        raise InputError("output directory does not exist", out)
    journal_path = journal_path or out + ".journal"
    from calib_cli.acquire.lockfile import hold

    with contextlib.ExitStack() as locks:
        # one recorder per output and per journal (issue 15): the second exits 3
        locks.enter_context(hold(out))
        if os.path.abspath(journal_path) != os.path.abspath(out):
            locks.enter_context(hold(journal_path))
        if os.path.exists(out) and not force:
            raise InputError("a recording exists here; pass --force to replace it, or choose "
                             "another --out", out)
        if os.path.exists(journal_path):
            if not force:
                raise InputError(f"a journal of an earlier recording exists (killed?): recover "
                                 f"it with `calib recover {journal_path} --out FILE.h5`, or pass "
                                 "--force to set it aside", journal_path)
            aside = f"{journal_path}.{time.strftime('%Y%m%dT%H%M%SZ', time.gmtime())}.old"
            os.replace(journal_path, aside)
            info(f"the earlier journal was set aside as {aside}")
        rv = _record(imu, port, can_interface, can_channel, table, table_port, plan_path,
                     duration, out, journal_path, keep_journal, settle_window, accel_still,
                     gyro_still, settle_timeout, segment_duration, reconnect_timeout,
                     gravity_tolerance, no_data_timeout, prof, plan, cprof, chamber_port)
        if as_json and rv == 0:
            output_json(out, "raw")
        return rv


def _source(prof, transport) -> str:
    if prof.format == "can":
        return (f"CAN {getattr(transport, 'interface', '?')}:{getattr(transport, 'channel', '?')}"
                f" (bitrate {getattr(transport, 'bitrate', None) or 'default'})")
    baud = (prof.transport or {}).get("baudrate", 115200)
    return f"serial port {getattr(transport, 'port', '?')} at {baud} baud"


def _record(imu, port, can_interface, can_channel, table, table_port, plan_path, duration,
            out, journal_path, keep_journal, settle_window, accel_still, gyro_still,
            settle_timeout, segment_duration, reconnect_timeout, gravity_tolerance,
            no_data_timeout, prof, plan, cprof=None, chamber_port=None):
    from calib_cli.acquire.profile import load_table_profile
    from calib_cli.acquire.session import Session, SettleConfig, journal_to_recording
    from calib_cli.acquire.table import ManualTable, SerialTable
    from calib_cli.acquire.transport import CanTransport, SerialTransport
    from calib_cli.io.h5 import write_raw

    if prof.format == "can":
        tr = prof.transport
        transport = CanTransport(can_interface or tr.get("interface", "socketcan"),
                                 can_channel or tr.get("channel", "can0"), tr.get("bitrate"))
    else:
        transport = SerialTransport(port, prof.transport)
    display = LiveDisplay(len(plan.segments))

    def ask(msg: str) -> str:
        with display.paused():
            return click.prompt(msg, default="", show_default=False, err=True)

    tprof = load_table_profile(table) if table else None
    if tprof is not None and tprof.kind == "serial":
        if not table_port:
            raise click.UsageError("a serial turntable needs --table-port")
        driver = SerialTable(tprof, table_port)
    elif plan_path:
        driver = ManualTable(ask)  # no motor: the operator places the unit
    else:
        driver = None
    chamber_drv = None
    if cprof is not None:  # issue 21: setpoints and soaks (acquire/chamber.py)
        from calib_cli.acquire.chamber import open_chamber

        chamber_drv = open_chamber(cprof, chamber_port, ask)
        chamber_drv.start()
    import tomllib

    try:
        noise = tomllib.loads(prof.raw_text or "").get("noise", {})
    except (tomllib.TOMLDecodeError, RecursionError):
        noise = {}
    # stillness limits: the options; else the profile's [noise]; else measured at the start
    measure = {}
    limits_from = []
    if accel_still is None:
        if "accel_std" in noise:
            limits_from.append("accel: 5x the profile's [noise] accel_std")
        else:
            measure["accel"] = True
        accel_still = max(0.05, 5.0 * float(noise.get("accel_std", 0.0)))
    else:
        limits_from.append("accel: --accel-still")
    if gyro_still is None:
        if "gyro_std" in noise:
            limits_from.append("gyro: 5x the profile's [noise] gyro_std")
        else:
            measure["gyro"] = True
        gyro_still = max(0.01, 5.0 * float(noise.get("gyro_std", 0.0)))
    else:
        limits_from.append("gyro: --gyro-still")
    cfg = SettleConfig(window_s=settle_window, accel_std=accel_still, gyro_std=gyro_still,
                       timeout_s=settle_timeout, default_duration_s=segment_duration,
                       reconnect_s=reconnect_timeout)
    session = Session(prof, transport, plan, journal_path, table=driver, settle=cfg,
                      display=display,
                      header_extra={"imu_profile_path": prof.path,
                                    "table_profile": tprof.name if tprof else None,
                                    "chamber_profile": cprof.name if cprof else None})
    session.chamber, session.chamber_profile = chamber_drv, cprof
    session.source = _source(prof, transport)
    session.no_data_s = no_data_timeout
    session.gravity_tol_deg = gravity_tolerance
    old_term = signal.signal(signal.SIGTERM, _raise_interrupt)
    interrupted = False
    try:
        session.start()
        if plan_path and measure:
            _measure_limits(session, measure, limits_from)
        elif limits_from:
            session.limits_from = "; ".join(limits_from)
        if plan_path:
            session.run_plan()
        else:
            session.run_free(duration)
    except KeyboardInterrupt:
        interrupted = True
        if not plan_path and duration is None:
            session.finished = True  # an open-ended log ends with Ctrl-C
        if not session.n_rows:  # nothing recorded: no stale journal, and say why
            display.close()
            with contextlib.suppress(Exception):
                session.close()
            with contextlib.suppress(OSError):
                os.unlink(journal_path)
            raise InputError(f"interrupted before any valid frame arrived from "
                             f"{session.source}; nothing was recorded (check the port, the "
                             "baud rate or CAN channel, and that the unit is streaming)",
                             journal_path) from None
    except BaseException as exc:
        display.close()
        with contextlib.suppress(Exception):
            session.close()
        if driver is not None:
            with contextlib.suppress(Exception):
                driver.stop()
        if session.n_rows and "calib recover" not in getattr(exc, "message", ""):
            err_console.print(f"calib: the journal {journal_path} keeps what was recorded "
                              "(calib recover)", markup=False)
        else:  # nothing recorded: leave nothing behind
            with contextlib.suppress(OSError):
                os.unlink(journal_path)
        raise
    finally:
        signal.signal(signal.SIGTERM, old_term)
    display.close(session)
    if session.chamber is not None:  # the chamber stays at its last setpoint
        with contextlib.suppress(Exception):
            session.chamber.close()
    if driver is not None:
        with contextlib.suppress(Exception):
            driver.stop()
            driver.close()
    counts = session.close()
    rec = journal_to_recording(journal_path)
    inputs = [p for p in (plan_path, prof.path, tprof.path if tprof else None,
                         cprof.path if cprof and cprof.kind != "manual" else None) if p]
    try:
        write_raw(out, rec, inputs)
        if session.device_info:  # what the recorder set on the unit, and read back
            from calib_cli.acquire.device import write_device_info

            write_device_info(out, prof, session.device_info)
    except CalibError as exc:  # a full disk: the journal keeps the recording (issue 37)
        exc.message += f"; the journal {journal_path} keeps the recording (calib recover)"
        raise
    if not keep_journal:
        os.unlink(journal_path)
    info(f"recorded {len(rec)} samples, {len(rec.segments)} segments -> {out}; "
         f"checksum errors {counts['checksum_errors']}, dropped frames {counts['gaps']}, "
         f"disconnects {counts['disconnects']}")
    if interrupted and not Ctx.quiet:
        err_console.print("calib: interrupted" + ("" if session.finished else
                                                  " before the plan was finished"), markup=False)
    return 130 if interrupted and not session.finished else 0


START_NOISE_S = 1.0  # s of data measured at the start (at least 2 stillness windows)
START_NOISE_K = 5.0  # limit = K x the quietest measured std (as from a profile's [noise])


def _measure_limits(session, measure: dict, limits_from: list) -> None:
    """Stillness limits measured at the start where neither an option nor the
    profile's [noise] gives them: never below the defaults (0.05 m/s^2,
    0.01 rad/s), raised to 5x the std of the quietest stillness window of
    the first second (a unit whose own noise is above the defaults)."""
    import numpy as np

    cfg = session.cfg
    a, g = session.measure_noise(max(START_NOISE_S, 2 * cfg.window_s))
    if "accel" in measure and np.isfinite(a):
        cfg.accel_std = max(cfg.accel_std, START_NOISE_K * a)
        limits_from.append(f"accel: max(0.05, 5x {a:.3g}) measured at the start")
    if "gyro" in measure and np.isfinite(g):
        cfg.gyro_std = max(cfg.gyro_std, START_NOISE_K * g)
        limits_from.append(f"gyro: max(0.01, 5x {g:.3g}) measured at the start")
    session.limits_from = "; ".join(limits_from)
    info(f"stillness limits: accel std < {cfg.accel_std:.3g} m/s^2, gyro std < "
         f"{cfg.gyro_std:.3g} rad/s ({session.limits_from}; --accel-still/--gyro-still "
         "set them)")
