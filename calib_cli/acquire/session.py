"""The session runner behind ``calib record``: follow a plan, read the IMU,
journal every sample, and turn the journal into a Recording.

Two threads: a reader (transport -> decoder -> SampleStream, reconnecting
after a disconnect) and the caller's thread, which commands the table, waits
until the unit is settled (table status, then stillness in the IMU data),
tags the samples of each segment with its plan index (-1 in the transitions,
which are recorded too), appends everything to the journal and refreshes
the display. ``journal_to_recording`` is the one path from a journal to a
Recording: used at a clean end, after Ctrl-C and by ``calib recover``.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import numpy as np

from calib_cli.acquire.chamber import soak_segment
from calib_cli.acquire.codec import SampleStream, make_decoder
from calib_cli.acquire.journal import META_COLS, JournalWriter, read_journal
from calib_cli.acquire.profile import ImuProfile
from calib_cli.acquire.table import ManualTable, turn_target
from calib_cli.acquire.transport import TransportLost
from calib_cli.data import Recording
from calib_cli.errors import InputError
from calib_cli.io.csvlog import segments_from_column
from calib_cli.io.plan import Plan, parse_plan
from calib_cli.model.effects import Layout
from calib_cli.plan import plan_layout


@dataclass
class SettleConfig:
    """Stillness: over the last ``window_s`` seconds after the table reports
    it is in position, every accel channel's std < accel_std (m/s^2) and
    every gyro channel's std < gyro_std (rad/s)."""

    window_s: float = 0.5
    accel_std: float = 0.05
    gyro_std: float = 0.01
    timeout_s: float = 120.0
    poll_s: float = 0.1
    default_duration_s: float = 10.0
    reconnect_s: float = 30.0


def free_run_plan(duration: float | None) -> str:
    """The plan of a free-running log: one segment of unknown attitude."""
    dur = f"\nduration_s = {float(duration)}" if duration else ""
    return (f'name = "free-run"\nkind = "static"\n\n[[segment]]\nlabel = "log"{dur}\n')


class Interrupted(Exception):
    pass


class Session:
    def __init__(self, prof: ImuProfile, transport, plan: Plan, journal_path: str,
                 table=None, settle: SettleConfig | None = None, display=None,
                 header_extra: dict | None = None):
        self.prof, self.transport, self.plan = prof, transport, plan
        self.table = table if table is not None else None
        self.cfg = settle or SettleConfig()
        self.display = display
        self.stream = SampleStream(prof)
        self.decoder = make_decoder(prof)
        self.nch = self.stream.n_channels
        self.nsens = sum(1 for c in prof.channels if c != "temp") // 2
        header = {"format": "calib-journal", "version": 1, "profile": prof.name,
                  "profile_text": prof.raw_text, "channels": list(prof.channels),
                  "columns": list(META_COLS) + list(prof.channels), "plan_text": plan.text,
                  "plan_path": plan.path, "rate_hz": prof.rate_hz,
                  "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
        header.update(header_extra or {})
        self.journal = JournalWriter(journal_path, header)
        self._lock = threading.Lock()
        self._queue: list[np.ndarray] = []
        self._stop = threading.Event()
        self._reader = None
        self.error: str | None = None
        # tagging state
        self.seg_index = -1
        self.seg_t0 = None
        self.seg_dur = None
        self.seg_done = False
        self.n_rows = 0
        self.recent: list[np.ndarray] = []
        self.recent_t = 0.0
        self.state = "starting"
        self.current_label = ""
        self.progress = 0.0
        self.finished = False
        self.rate_meas = 0.0
        self._rate_hist: list[tuple[float, int]] = []
        # guard rails (issue 15); the CLI sets them, library users may
        self.source = "the device"  # named in the no-data message
        self.no_data_s: float | None = None  # no valid frame this long after start: stop
        self.gravity_tol_deg: float | None = None  # position check against attitude_deg
        self._t_open: float | None = None
        # climatic chamber (issue 21, acquire/chamber.py); the CLI sets them
        self.chamber = None
        self.chamber_profile = None
        self.device_info: dict = {}  # the configuration exchange (acquire/device.py)

    # -- reader thread -------------------------------------------------------
    def _read_loop(self) -> None:
        can = self.prof.format == "can"
        outage = False  # lost, and no frame since: a port that flaps while the device
        # is away is one disconnect, not one per failed reopen
        while not self._stop.is_set():
            try:
                if can:
                    items = []
                    for cid, data in self.transport.read_messages():
                        items += self.decoder.feed_message(cid, data)
                else:
                    items = self.decoder.feed(self.transport.read())
            except TransportLost:
                if not outage:
                    self.stream.mark_disconnect()
                outage = True
                self.decoder.buf = bytearray() if not can else self.decoder.buf
                if not self.transport.reconnect(self.cfg.reconnect_s, self._stop):
                    if not self._stop.is_set():
                        self.error = "the device did not come back after a disconnect"
                    return
                continue
            except Exception as exc:  # noqa: BLE001 - reported by the main thread
                self.error = f"reader failed: {type(exc).__name__}: {exc}"
                return
            rows = self.stream.push(items, time.monotonic())
            outage = outage and not items
            if len(rows):
                with self._lock:
                    self._queue.append(rows)

    def counts(self) -> dict:
        c = dict(self.stream.counts)
        c["garbage_bytes"] = int(self.decoder.garbage_bytes)
        c["lost_frames"] = c["checksum_errors"] + c["gaps"]
        return c

    # -- main thread: draining, tagging, journal ---------------------------
    def pump(self, dt: float = 0.02) -> np.ndarray:
        """Wait ``dt``, take the new rows, tag, journal. Returns the new rows."""
        time.sleep(dt)
        if self.error:
            raise InputError(self.error, getattr(self.transport, "port", None)
                             or getattr(self.transport, "channel", None))
        with self._lock:
            batch, self._queue = self._queue, []
        if not batch and self.n_rows == 0 and self.no_data_s and self._t_open is not None \
                and time.monotonic() - self._t_open > self.no_data_s:
            raise InputError(
                f"no valid frame from {self.source} in {self.no_data_s:g} s "
                f"({int(self.decoder.garbage_bytes)} bytes not understood): check the port, "
                "the baud rate or CAN channel, that the unit is powered and streaming, and "
                f"that the profile {self.prof.name!r} matches its output", None)
        if not batch:
            self._tick()
            return np.empty((0, 2 + self.nch))
        rows = np.concatenate(batch)
        seg = np.full(len(rows), -1.0)
        if self.seg_index >= 0 and not self.seg_done:
            if self.seg_t0 is None:
                self.seg_t0 = rows[0, 0]
            t = rows[:, 0]
            inside = t < self.seg_t0 + self.seg_dur if self.seg_dur else np.ones(len(t), bool)
            seg[inside] = self.seg_index
            if self.seg_dur:
                self.progress = min((t[-1] - self.seg_t0) / self.seg_dur, 1.0)
                if not inside.all():
                    self.seg_done = True
        out = np.empty((len(rows), 3 + self.nch))
        out[:, :2] = rows[:, :2]
        out[:, 2] = seg
        out[:, 3:] = rows[:, 2:]
        self.journal.append(out)
        self.n_rows += len(rows)
        self.recent.append(rows)
        # keep about window_s of rows for the stillness test
        keep, tot = [], 0
        for r in reversed(self.recent):
            keep.append(r)
            tot += len(r)
            if tot * 1.0 / self.prof.rate_hz > self.cfg.window_s * 2:
                break
        self.recent = keep[::-1]
        self._tick()
        return rows

    def _tick(self) -> None:
        now = time.monotonic()
        self._rate_hist.append((now, self.n_rows))
        while len(self._rate_hist) > 2 and now - self._rate_hist[0][0] > 1.0:
            self._rate_hist.pop(0)
        (t0, n0), (t1, n1) = self._rate_hist[0], self._rate_hist[-1]
        self.rate_meas = (n1 - n0) / (t1 - t0) if t1 > t0 else 0.0
        self.journal.maybe_flush(self.counts())
        if self.display is not None:
            self.display(self)

    def _still(self, since: float) -> bool:
        if not self.recent:
            return False
        rows = np.concatenate(self.recent)
        rows = rows[rows[:, 0] >= rows[-1, 0] - self.cfg.window_s]
        if len(rows) < 5 or rows[0, 0] < since:
            return False
        n = self.nsens
        a, g = rows[:, 2:2 + n], rows[:, 2 + n:2 + 2 * n]
        return bool(np.all(a.std(axis=0) < self.cfg.accel_std)
                    and np.all(g.std(axis=0) < self.cfg.gyro_std))

    def _measured_std(self) -> tuple[float, float]:
        """The largest accel and gyro channel std over the last stillness window."""
        if not self.recent:
            return float("nan"), float("nan")
        rows = np.concatenate(self.recent)
        rows = rows[rows[:, 0] >= rows[-1, 0] - self.cfg.window_s]
        n = self.nsens
        if len(rows) < 2:
            return float("nan"), float("nan")
        return (float(rows[:, 2:2 + n].std(axis=0).max()),
                float(rows[:, 2 + n:2 + 2 * n].std(axis=0).max()))

    def measure_noise(self, seconds: float, timeout_s: float = 30.0) -> tuple[float, float]:
        """Stillness limits measured at the start: record ``seconds`` of data
        (journalled, outside any segment) and return the largest channel std
        of accel and gyro in the quietest ``window_s`` stretch of it (a unit
        picked up for part of the time does not raise the figure)."""
        rows, got = [], 0
        t_end = time.monotonic() + timeout_s
        while time.monotonic() < t_end:
            r = self.pump()
            if len(r):
                rows.append(r)
                got += len(r)
                if rows[-1][-1, 0] - rows[0][0, 0] >= seconds:
                    break
        if not rows:
            return float("nan"), float("nan")
        x = np.concatenate(rows)
        n = self.nsens
        m = max(int(round(self.cfg.window_s * self.prof.rate_hz)), 5)
        best = (float("inf"), float("inf"))
        for k in range(0, max(len(x) - m, 0) + 1, max(m // 2, 1)):
            w = x[k:k + m]
            if len(w) < 5:
                continue
            a = float(w[:, 2:2 + n].std(axis=0).max())
            g = float(w[:, 2 + n:2 + 2 * n].std(axis=0).max())
            if a + g * 9.81 < best[0] + best[1] * 9.81:
                best = (a, g)
        self.start_noise = best if np.isfinite(best[0]) else (float("nan"), float("nan"))
        return self.start_noise

    def _last_time(self) -> float:
        return self.recent[-1][-1, 0] if self.recent else -np.inf

    def _limits_source(self) -> str:
        sn = getattr(self, "start_noise", None)
        why = getattr(self, "limits_from", "")
        out = f" (limits {why})" if why else ""
        if sn is not None and np.isfinite(sn[0]):
            out += (f"; at the start the quietest {self.cfg.window_s:g} s measured accel "
                    f"{sn[0]:.4g} m/s^2, gyro {sn[1]:.4g} rad/s")
        return out

    def wait_settled(self, check_still: bool = True) -> None:
        """Table status first, then stillness of the IMU data."""
        self.state = "moving"
        t_end = time.monotonic() + self.cfg.timeout_s
        next_poll = 0.0
        while True:
            self.pump()
            if time.monotonic() > t_end:
                raise InputError(f"the unit did not settle within {self.cfg.timeout_s:g} s "
                                 "(table status or motion in the IMU data)")
            if time.monotonic() >= next_poll:
                next_poll = time.monotonic() + self.cfg.poll_s
                if self.table is None or self.table.settled():
                    break
        if not check_still:
            return
        self.state = "settling"
        since = self._last_time()
        while not self._still(since):
            self.pump()
            if time.monotonic() > t_end:
                a_std, g_std = self._measured_std()
                raise InputError(
                    f"the unit did not keep still within {self.cfg.timeout_s:g} s: measured "
                    f"std accel {a_std:.4g} m/s^2 (limit {self.cfg.accel_std:.3g}, "
                    f"--accel-still), gyro {g_std:.4g} rad/s (limit {self.cfg.gyro_std:.3g}, "
                    f"--gyro-still) over {self.cfg.window_s:g} s{self._limits_source()}; if the "
                    "unit was still, its noise is above the limits: raise them (or state "
                    "[noise] in the profile)")

    def record_segment(self, index: int, duration: float | None, schedule=None) -> None:
        """Tag the next ``duration`` seconds of samples with plan index ``index``
        (until interrupted when duration is None). ``schedule``: [(t_s, rate_rad_s), ...]
        table rate commands at those times from the segment's first sample."""
        self.seg_index, self.seg_t0, self.seg_dur, self.seg_done = index, None, duration, False
        self.state, self.progress = "recording", 0.0
        todo = list(schedule or [])
        while not self.seg_done:
            self.pump()
            while todo and self.seg_t0 is not None and self.progress * (duration or 0) >= todo[0][0]:
                self.table.set_rate(todo.pop(0)[1])
        self.seg_index = -1
        self.state = "done"

    # -- the plan ----------------------------------------------------------
    def configure_device(self) -> None:
        """The profile's configuration and go-to-measurement steps
        (acquire/device.py); their log and read-back go to ``device_info``."""
        prof = self.prof
        if prof.format == "can" or not (prof.configure or prof.start_steps):
            return
        from calib_cli.acquire.device import run_steps

        log: list[str] = []
        readback = run_steps(self.transport, prof, prof.configure, prof.rate_hz, "configure",
                             log)
        readback.update(run_steps(self.transport, prof, prof.start_steps, prof.rate_hz,
                                  "start", log))
        self.device_info = {"rate_hz": prof.rate_hz, "exchange": log, "readback": readback}

    def stop_device(self) -> None:
        """The profile's stop steps on exit (best effort: a unit that does not
        answer is left as it is, with a warning)."""
        prof = self.prof
        if prof.format == "can" or not prof.stop_steps or self.transport is None:
            return
        from calib_cli.acquire.device import run_steps
        from calib_cli.errors import warn

        log = self.device_info.setdefault("exchange", []) if self.device_info else []
        try:
            run_steps(self.transport, prof, prof.stop_steps, prof.rate_hz, "stop", log)
        except Exception as exc:  # noqa: BLE001 - closing must go on
            warn(f"the unit did not acknowledge the stop: {exc}")

    def start(self) -> None:
        self.transport.open()
        self.configure_device()
        self._t_open = time.monotonic()
        self._reader = threading.Thread(target=self._read_loop, daemon=True)
        self._reader.start()

    def run_plan(self) -> None:
        plan, table = self.plan, self.table
        current_att = None
        for i, seg in enumerate(plan.segments):
            self.current_label = f"{seg.label} ({i + 1}/{len(plan.segments)})"
            dur = seg.duration or self.cfg.default_duration_s
            kind = seg.kind
            manual = isinstance(table, ManualTable)
            if kind == "static" and seg.repeat_auto and manual:
                while True:
                    line = table.ask(f"[{seg.label}] place the unit in a new position, hold it "
                                     "still and press Enter (q + Enter when done)")
                    if line.strip().lower().startswith("q"):
                        break
                    self.wait_settled()
                    self.record_segment(i, dur)
                continue
            if seg.attitude is not None and table is not None:
                table.move(seg.attitude, seg.label)
                current_att = seg.attitude
            elif manual:
                table.move(None, seg.label)
            soak_segment(self, seg)  # a chamber setpoint: wait for the soak
            if kind == "static":
                self.wait_settled()
                self._check_gravity(seg, table, manual)
                self.record_segment(i, dur)
            elif kind == "rotating":
                if table is None or manual:
                    raise InputError(f"segment {seg.label!r} turns the table: it needs a "
                                     "motorised table (--table PROFILE --table-port PORT)",
                                     plan.path)
                self.wait_settled()
                if seg.table_rate is not None:  # a constant rate, reached before recording
                    table.set_rate(seg.table_rate)
                    self.wait_settled(check_still=False)
                    self.record_segment(i, dur)
                else:  # a profile: the cycle starts at rest, the table follows its holds
                    dur, schedule = rate_schedule(seg, plan.path)
                    self.record_segment(i, dur, schedule)
                table.stop()
            else:  # a turn of known angle
                self.wait_settled()
                self.seg_index, self.seg_t0, self.seg_dur, self.seg_done = i, None, None, False
                self.state = "turning"
                if manual:
                    table.turn(seg.rotation_axis_body, seg.rotation_angle, seg.label)
                else:
                    if abs(seg.rotation_angle) >= np.pi or current_att is None:
                        raise InputError(f"segment {seg.label!r}: a motorised turn needs a start "
                                         "attitude and less than 180 deg; use a manual table",
                                         plan.path)
                    current_att = turn_target(current_att, seg.rotation_axis_body,
                                              seg.rotation_angle)
                    table.move(current_att, seg.label)
                self.wait_settled()
                self.seg_done = True
                self.seg_index = -1
        self.finished = True

    def measured_gravity_angle(self, seg) -> float | None:
        """Angle (deg) between the gravity direction measured over the stillness
        window and the one ``seg.attitude`` implies (a triad only)."""
        if seg.attitude is None or self.nsens != 3 or not self.recent:
            return None
        from calib_cli.model.frames import attitude_to_rotation

        rows = np.concatenate(self.recent)
        rows = rows[rows[:, 0] >= rows[-1, 0] - self.cfg.window_s]
        a = rows[:, 2:5].mean(axis=0)
        if not np.all(np.isfinite(a)) or np.linalg.norm(a) == 0:
            return None
        up = attitude_to_rotation(np.asarray(seg.attitude)).inv().apply([0.0, 0.0, 1.0])
        c = float(np.dot(a, up) / np.linalg.norm(a))
        return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))

    def _check_gravity(self, seg, table, manual: bool) -> None:
        """Refuse a position whose gravity direction is not the planned one:
        ask the operator again (manual), or stop (a motorised table)."""
        if not self.gravity_tol_deg:
            return
        while True:
            ang = self.measured_gravity_angle(seg)
            if ang is None or ang <= self.gravity_tol_deg:
                return
            self.rejected_positions = getattr(self, "rejected_positions", 0) + 1
            if not manual:
                raise InputError(f"position {seg.label!r}: the unit measures gravity {ang:.0f} "
                                 f"deg away from the direction its attitude_deg states (limit "
                                 f"{self.gravity_tol_deg:g} deg): check the table's mounting "
                                 "and axes, or the plan", self.plan.path)
            table.ask(f"[{seg.label}] the unit reads gravity {ang:.0f} deg away from this "
                      "position: place it as asked, hold it still, then press Enter")
            self.wait_settled()

    def run_free(self, duration: float | None) -> None:
        self.current_label = "log"
        self.record_segment(0, duration)
        self.finished = duration is not None

    def close(self) -> dict:
        """Stop reading, take the last rows, close the journal. Returns the counts."""
        self._stop.set()
        if self._reader is not None:
            self._reader.join(2)
        try:
            self.pump(0.0)
        except InputError:
            pass
        if self._t_open is not None:
            self.stop_device()
        self.transport.close()
        counts = self.counts()
        counts["plan_finished"] = int(self.finished)
        self.journal.close(counts)
        return counts


def journal_to_recording(path: str) -> Recording:
    """A Recording from a journal (complete, or cut by a killed recorder)."""
    header, rows, counters, complete = read_journal(path)
    # rows a damaged journal cannot vouch for: non-finite values, time going back
    n0 = len(rows)
    chans = header["channels"]
    if "temp" in chans and len(rows):  # a unit that never sent its temperature
        k = 3 + list(chans).index("temp")
        if not np.isfinite(rows[:, k]).any():
            rows = np.delete(rows, k, axis=1)
            chans = [c for c in chans if c != "temp"]
    rows = rows[np.all(np.isfinite(rows), axis=1)]
    if len(rows):
        keep = np.ones(len(rows), bool)
        keep[1:] = rows[1:, 0] >= np.maximum.accumulate(rows[:, 0])[:-1]
        rows = rows[keep]
    dropped = n0 - len(rows)
    if not len(rows):
        raise InputError("the journal holds no samples", str(path))
    plan = parse_plan(header.get("plan_text", ""), header.get("plan_path", str(path)))
    n = sum(1 for c in chans if c != "temp") // 2
    data = rows[:, 3:]
    seg = rows[:, 2].astype(int)
    segments = segments_from_column(seg, plan, str(path))
    if plan.kind == "rimu" or "a0" in chans:
        layout = plan_layout(plan) if plan.kind == "rimu" else Layout(n=n)
    else:
        layout = plan_layout(plan)
    t = rows[:, 0] - rows[0, 0]
    table_angle = table_rate = None
    if any(s.kind == "rotating" for s in segments):
        # the commanded (nominal) table rate, and the angle it turns from each
        # rotating segment's first sample, as calib simulate stores them
        table_angle, table_rate = np.full(len(t), np.nan), np.zeros(len(t))
        for s in segments:
            if s.kind == "rotating" and s.table_rate is not None:
                table_rate[s.slice] = s.table_rate
                table_angle[s.slice] = s.table_rate * (t[s.slice] - t[s.start])
    counters = {k: int(v) for k, v in counters.items()
                if isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v)}
    counters["journal_complete"] = int(complete)
    counters["samples"] = len(rows)
    if dropped:
        counters["journal_rows_dropped"] = dropped
    return Recording(time=t, accel=data[:, :n], gyro=data[:, n:2 * n],
                     table_angle=table_angle, table_rate=table_rate,
                     segments=tuple(segments), site=plan.site, plan_kind=plan.kind,
                     plan_text=plan.text, serial=plan.serial, layout=layout,
                     temp=data[:, 2 * n] if "temp" in chans else None, counters=counters)


def rate_schedule(seg, path=None) -> tuple[float, list]:
    """(duration s, [(t_s, rate_rad_s), ...]) of the rate commands that run a rotating
    segment's profile on a table that ramps by itself: the segment's ``rate_profile``
    knots, else the default profile over ``duration_s`` (docs/simulate.md); each
    command at the start of a ramp. A sinusoidal ``rate_oscillation`` needs a table
    that follows a profile and is refused."""
    from calib_cli.sim.turntable_plans import rate_profile

    if "rate_oscillation" in seg.extra:
        raise InputError(f"segment {seg.label!r}: rate_oscillation cannot be run by rate "
                         "commands; give rate_profile knots", path)
    knots = seg.extra.get("rate_profile") or rate_profile(seg.duration or 120.0)
    try:
        kt = [float(k[0]) for k in knots]
        kr = [float(k[1]) * np.pi / 180.0 for k in knots]
    except (TypeError, ValueError, IndexError):
        raise InputError(f"segment {seg.label!r}: rate_profile must be [[t_s, rate_dps], ...]",
                         path) from None
    schedule = [(kt[i] - kt[0], kr[i + 1]) for i in range(len(kt) - 1) if kr[i + 1] != kr[i]]
    return kt[-1] - kt[0], schedule
