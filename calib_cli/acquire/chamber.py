"""Climatic chambers for ``calib record`` (docs/acquisition.md, docs/thermal.md):
the chamber profile (TOML), the drivers (an SCPI-style text protocol, Modbus
RTU, and a manual chamber: the operator is prompted) and the soak rule.

A plan segment with ``chamber_temp_degC`` sets the chamber's setpoint before
that segment is recorded; ``calib record`` then waits for the soak:

- the setpoint is approached at no more than the ramp-rate limit, the
  smaller of the plan's ``chamber_ramp_dpm`` and the profile's
  ``max_ramp_dpm`` (a chamber with a ramp command or register is given the
  rate; otherwise calib moves the setpoint itself in steps);
- the chamber's read-back is within max(1 degC, tolerance) of the setpoint;
- the unit's own temperature (the IMU's ``temp`` channel; the chamber's
  read-back when the profile has none) moves by no more than
  ``chamber_soak_tol_degC`` (max - min) over the last ``chamber_soak_s``;
- if that takes longer than ``chamber_soak_timeout_s`` the recording stops
  (exit 3, the journal keeps what was recorded).

The soak keys are read from the segment, else the plan's top level. A
segment with ``chamber_soak = false`` (a ramp design) sets the chamber going
(ramp rate, setpoint) and is recorded at once, without waiting.
"""

from __future__ import annotations

import re
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from calib_cli.acquire import modbus
from calib_cli.errors import InputError

SOAK_DEFAULTS = {"chamber_soak_tol_degC": 0.1, "chamber_soak_s": 600.0,
                 "chamber_soak_timeout_s": 7200.0}
AIR_TOL = 1.0  # degC: the chamber's read-back is this close to its setpoint (or the tolerance)
POLL_S = 0.2  # s between chamber read-backs
CHAMBER_COMMANDS = ("set_temp", "query_temp", "set_ramp", "start", "stop")
TEMPLATE_FIELDS = {"set_temp": {"temp_degC"}, "set_ramp": {"rate_dpm"}, "query_temp": set(),
                   "start": set(), "stop": set()}
PROFILE_KEYS = {
    "": {"name", "description", "kind", "terminator", "timeout_s", "max_ramp_dpm",
         "min_temp_degC", "max_temp_degC", "transport", "commands", "responses", "replies",
         "modbus"},
    "transport": {"baudrate", "bytesize", "parity", "stopbits", "timeout_s"},
    "commands": set(CHAMBER_COMMANDS),
    "responses": {"ack", "temp"},
    "replies": {"ack", "temp", "error"},
    "modbus": {"slave", "setpoint_register", "temp_register", "temp_function", "scale_degC",
               "signed", "ramp_register", "ramp_scale_dpm"},
}


@dataclass(frozen=True)
class ChamberProfile:
    name: str
    path: str
    kind: str  # scpi | modbus | manual
    transport: dict = field(default_factory=dict)
    terminator: str = "\r\n"
    timeout_s: float = 2.0  # reply timeout
    max_ramp_dpm: float | None = None
    min_temp_degC: float = -100.0
    max_temp_degC: float = 200.0
    commands: dict = field(default_factory=dict)
    responses: dict = field(default_factory=dict)  # compiled patterns
    replies: dict = field(default_factory=dict)  # the emulator's reply templates
    modbus: dict = field(default_factory=dict)


def parse_chamber_profile(text: str, path: str = "<chamber>") -> ChamberProfile:
    from calib_cli.io import schema

    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"not valid TOML: {exc}", path) from None
    except RecursionError:
        raise InputError("not valid TOML: nested too deeply", path) from None
    schema.check_profile_keys(raw, PROFILE_KEYS, path)
    if "transport" in raw:
        schema.check_transport(raw["transport"], path)
    try:
        return _parse(raw, path)
    except (TypeError, ValueError, AttributeError, KeyError, OverflowError) as exc:
        raise InputError(f"malformed chamber profile: {type(exc).__name__}: {exc}", path) from None


def _parse(raw: dict, path: str) -> ChamberProfile:
    kind = raw.get("kind", "scpi")
    if kind not in ("scpi", "modbus", "manual"):
        raise InputError(f"kind must be scpi, modbus or manual, got {kind!r}", path)
    name = str(raw.get("name", Path(path).stem))
    ramp = raw.get("max_ramp_dpm")
    if ramp is not None and (isinstance(ramp, bool) or not float(ramp) > 0):
        raise InputError(f"max_ramp_dpm must be a number > 0, got {ramp!r}", path)
    lo, hi = float(raw.get("min_temp_degC", -100.0)), float(raw.get("max_temp_degC", 200.0))
    if not lo < hi:
        raise InputError("min_temp_degC must be below max_temp_degC", path)
    kw = dict(name=name, path=path, kind=kind, transport=raw.get("transport", {}),
              terminator=str(raw.get("terminator", "\r\n")),
              timeout_s=float(raw.get("timeout_s", 2.0)),
              max_ramp_dpm=None if ramp is None else float(ramp), min_temp_degC=lo,
              max_temp_degC=hi)
    if kind == "scpi":
        import string

        cmds = raw.get("commands", {})
        for c in ("set_temp", "query_temp"):
            if c not in cmds:
                raise InputError(f"[commands] needs {c!r}", path)
        for c, tpl in cmds.items():
            fields = {f for _, f, _, _ in string.Formatter().parse(str(tpl)) if f}
            bad = {f.split(":")[0] for f in fields} - TEMPLATE_FIELDS[c]
            if bad:
                raise InputError(f"commands.{c}: unknown template field(s) "
                                 f"{', '.join(sorted(bad))} (known: "
                                 f"{', '.join(sorted(TEMPLATE_FIELDS[c])) or 'none'})", path)
        resp = {}
        for k, v in raw.get("responses", {}).items():
            try:
                resp[k] = re.compile(v)
            except re.error as exc:
                raise InputError(f"responses.{k} is not a valid regular expression: {exc}",
                                 path) from None
        if "temp" not in resp or "temp_degC" not in resp["temp"].groupindex:
            raise InputError("responses.temp must be a pattern with a named group "
                             "(?P<temp_degC>...)", path)
        kw.update(commands=dict(cmds), responses=resp, replies=raw.get("replies", {}))
    elif kind == "modbus":
        mb = dict(raw.get("modbus", {}))
        for k in ("setpoint_register", "temp_register"):
            if k not in mb:
                raise InputError(f"[modbus] needs {k!r}", path)
        for k in ("slave", "setpoint_register", "temp_register", "ramp_register"):
            if k in mb and (isinstance(mb[k], bool) or not isinstance(mb[k], int)
                            or not 0 <= mb[k] <= (247 if k == "slave" else 0xFFFF)):
                raise InputError(f"modbus.{k} must be an integer register address "
                                 f"(slave 0..247), got {mb[k]!r}", path)
        if mb.get("temp_function", 3) not in (3, 4):
            raise InputError("modbus.temp_function must be 3 (holding) or 4 (input registers)",
                             path)
        mb.setdefault("slave", 1)
        mb.setdefault("temp_function", 3)
        mb.setdefault("scale_degC", 0.1)
        mb.setdefault("signed", True)
        mb.setdefault("ramp_scale_dpm", 0.1)
        if not float(mb["scale_degC"]) > 0 or not float(mb["ramp_scale_dpm"]) > 0:
            raise InputError("modbus.scale_degC and ramp_scale_dpm must be > 0", path)
        kw["modbus"] = mb
    return ChamberProfile(**kw)


def load_chamber_profile(name) -> ChamberProfile:
    from calib_cli.acquire.profile import _read_named, resolve_profile

    if str(name) == "manual":
        return ChamberProfile(name="manual", path="manual", kind="manual")
    p = resolve_profile(str(name), "chamber")
    return parse_chamber_profile(_read_named(str(name), p, "chamber"), p)


# ---------------------------------------------------------------------------
# drivers


class _Serial:
    def __init__(self, prof: ChamberProfile, port: str):
        import serial

        self.prof, self.port = prof, port
        t = prof.transport
        try:
            self.ser = serial.Serial(port, baudrate=int(t.get("baudrate", 9600)),
                                     bytesize=int(t.get("bytesize", 8)),
                                     parity=str(t.get("parity", "N")),
                                     stopbits=float(t.get("stopbits", 1)),
                                     timeout=float(t.get("timeout_s", prof.timeout_s)))
        except (serial.SerialException, ValueError, OSError) as exc:
            raise InputError(f"cannot open chamber port: {exc}", port) from None
        self.ser.reset_input_buffer()

    def close(self) -> None:
        self.ser.close()


class ScpiChamber(_Serial):
    """Line commands from the profile's templates, replies matched by its patterns."""

    motorised = True

    def __init__(self, prof: ChamberProfile, port: str):
        super().__init__(prof, port)
        self.term = prof.terminator.encode()

    def _send(self, name: str, **kw) -> str:
        self.ser.reset_input_buffer()
        self.ser.write(self.prof.commands[name].format(**kw).encode() + self.term)
        raw = self.ser.read_until(self.term[-1:])
        if not raw:
            raise InputError(f"the chamber did not answer {name!r}", self.port)
        return raw.decode("ascii", "replace").strip()

    def _command(self, name: str, **kw) -> None:
        reply = self._send(name, **kw)
        ack = self.prof.responses.get("ack")
        if ack is not None and not ack.search(reply):
            raise InputError(f"the chamber refused {name!r}: {reply!r}", self.port)

    def start(self) -> None:
        if "start" in self.prof.commands:
            self._command("start")

    def set_temp(self, degc: float) -> None:
        self._command("set_temp", temp_degC=float(degc))

    def set_ramp(self, dpm: float) -> bool:
        if "set_ramp" not in self.prof.commands:
            return False
        self._command("set_ramp", rate_dpm=float(dpm))
        return True

    def read_temp(self) -> float:
        reply = self._send("query_temp")
        m = self.prof.responses["temp"].search(reply)
        if m is None:
            raise InputError(f"unexpected chamber temperature reply {reply!r}", self.port)
        return float(m.group("temp_degC"))

    def stop(self) -> None:
        if "stop" in self.prof.commands:
            self._command("stop")


class ModbusChamber(_Serial):
    """Modbus RTU: setpoint written to a holding register (06), temperature
    read from a holding or input register (03/04), in counts of scale_degC."""

    motorised = True

    def __init__(self, prof: ChamberProfile, port: str):
        super().__init__(prof, port)
        self.mb = prof.modbus

    def _transact(self, request: bytes, function: int) -> list[int]:
        self.ser.reset_input_buffer()
        self.ser.write(request)
        want = modbus.reply_length(function)
        buf = b""
        t_end = time.monotonic() + float(self.prof.timeout_s)
        while len(buf) < want and time.monotonic() < t_end:
            buf += self.ser.read(want - len(buf))
            if len(buf) >= 5 and buf[1] == (function | 0x80):
                break
        if not buf:
            raise InputError("the chamber did not answer (Modbus RTU: check the slave "
                             "address, baud rate and parity)", self.port)
        try:
            return modbus.parse_reply(buf, int(self.mb["slave"]), function)
        except modbus.ModbusError as exc:
            raise InputError(f"Modbus reply: {exc}", self.port) from None

    def _counts(self, value: float, scale: float) -> int:
        c = int(round(value / scale))
        lo, hi = (-0x8000, 0x7FFF) if self.mb.get("signed", True) else (0, 0xFFFF)
        if not lo <= c <= hi:
            raise InputError(f"{value:g} does not fit a 16-bit register at {scale:g} per count",
                             self.prof.path)
        return c

    def start(self) -> None:
        pass

    def set_temp(self, degc: float) -> None:
        mb = self.mb
        self._transact(modbus.write_request(int(mb["slave"]), int(mb["setpoint_register"]),
                                            self._counts(degc, float(mb["scale_degC"]))),
                       modbus.WRITE_SINGLE)

    def set_ramp(self, dpm: float) -> bool:
        mb = self.mb
        if "ramp_register" not in mb:
            return False
        self._transact(modbus.write_request(int(mb["slave"]), int(mb["ramp_register"]),
                                            self._counts(dpm, float(mb["ramp_scale_dpm"]))),
                       modbus.WRITE_SINGLE)
        return True

    def read_temp(self) -> float:
        mb = self.mb
        fn = int(mb.get("temp_function", 3))
        v = self._transact(modbus.read_request(int(mb["slave"]), int(mb["temp_register"]), 1, fn),
                           fn)[0]
        if mb.get("signed", True):
            v = modbus.to_signed(v)
        return v * float(mb["scale_degC"])

    def stop(self) -> None:
        pass


class ManualChamber:
    """The operator sets the chamber; ``ask`` shows a prompt and waits for Enter."""

    motorised = False

    def __init__(self, ask):
        self.ask = ask

    def start(self) -> None:
        pass

    def stop(self) -> None:
        pass

    def close(self) -> None:
        pass


def open_chamber(prof: ChamberProfile, port: str | None, ask):
    if prof.kind == "manual":
        return ManualChamber(ask)
    if not port:
        raise InputError("a serial chamber needs --chamber-port", prof.path)
    return (ScpiChamber if prof.kind == "scpi" else ModbusChamber)(prof, port)


# ---------------------------------------------------------------------------
# the soak


def _num(v, key, where, path, lo=0.0):
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v) or v <= lo:
        raise InputError(f"{where}{key} must be a number > {lo:g}, got {v!r}", path)
    return float(v)


_NO_RAMP = ("segment {label!r} ramps without a soak (chamber_soak = false): the chamber must "
            "ramp by itself (a set_ramp command or ramp_register in its profile), or the plan "
            "must leave out the ramp-rate limit")


def soak_rule(plan, seg) -> dict:
    """The soak rule and ramp limit of a segment (segment keys, else the plan's)."""
    out = {"chamber_soak": seg.extra.get("chamber_soak", True) is not False}
    for k, d in SOAK_DEFAULTS.items():
        v = seg.extra.get(k, plan.extra.get(k, d))
        out[k] = _num(v, k, f"segment {seg.label!r}: " if k in seg.extra else "", plan.path)
    r = seg.extra.get("chamber_ramp_dpm", plan.extra.get("chamber_ramp_dpm"))
    out["chamber_ramp_dpm"] = None if r is None else _num(r, "chamber_ramp_dpm", "", plan.path)
    return out


def check_plan(plan, prof: ChamberProfile | None) -> list[str]:
    """Refuse setpoints the chamber cannot reach (exit 3 naming the plan);
    return warnings (a ramp rate above the chamber's limit is limited)."""
    sets = [(s, s.extra["chamber_temp_degC"]) for s in plan.segments
            if "chamber_temp_degC" in s.extra]
    if not sets:
        return []
    if prof is None:
        raise InputError("the plan sets chamber_temp_degC: give --chamber PROFILE "
                         "--chamber-port PORT (or --chamber manual)", plan.path)
    warnings = []
    for s, v in sets:
        v = _num(v, "chamber_temp_degC", f"segment {s.label!r}: ", plan.path, lo=-np.inf)
        if not prof.min_temp_degC <= v <= prof.max_temp_degC:
            raise InputError(f"segment {s.label!r}: chamber_temp_degC {v:g} is outside the "
                             f"chamber's range {prof.min_temp_degC:g}..{prof.max_temp_degC:g} "
                             f"degC ({prof.path})", plan.path)
        rule = soak_rule(plan, s)
        r = rule["chamber_ramp_dpm"]
        native = "set_ramp" in prof.commands or "ramp_register" in prof.modbus
        if not rule["chamber_soak"] and ramp_limit(rule, prof) and prof.kind != "manual" \
                and not native:
            raise InputError(_NO_RAMP.format(label=s.label), prof.path)
        if r is not None and prof.max_ramp_dpm is not None and r > prof.max_ramp_dpm:
            msg = (f"chamber_ramp_dpm {r:g} is above the chamber's limit {prof.max_ramp_dpm:g} "
                   "degC/min: the chamber's limit is used")
            if msg not in warnings:
                warnings.append(msg)
    return warnings


def ramp_limit(rule: dict, prof: ChamberProfile | None) -> float | None:
    rates = [r for r in (rule.get("chamber_ramp_dpm"), prof.max_ramp_dpm if prof else None)
             if r is not None]
    return min(rates) if rates else None


class Soak:
    """Drives one setpoint change and waits for the soak (see the module
    docstring). ``temp_col``: the journal column of the IMU's temperature in
    the rows ``session.pump`` returns (None: the chamber's read-back)."""

    def __init__(self, session, chamber, prof: ChamberProfile, target: float, rule: dict,
                 temp_col: int | None, label: str = ""):
        self.s, self.ch, self.prof = session, chamber, prof
        self.target, self.rule, self.col, self.label = float(target), rule, temp_col, label
        self.hist: list[tuple[float, float]] = []  # (time s, unit temperature)

    def _take(self, rows) -> None:
        if self.col is not None and len(rows):
            self.hist += list(zip(rows[:, 0].tolist(), rows[:, self.col].tolist(), strict=True))

    def _stable(self) -> tuple[bool, float]:
        """(stable, spread over the window)."""
        if not self.hist:
            return False, float("nan")
        t_now = self.hist[-1][0]
        win = self.rule["chamber_soak_s"]
        k = 0
        while k < len(self.hist) and self.hist[k][0] < t_now - win:
            k += 1
        self.hist = self.hist[max(k - 1, 0):]
        if self.hist[0][0] > t_now - win:
            return False, float("nan")
        v = np.array([x for _, x in self.hist])
        spread = float(v.max() - v.min())
        return spread <= self.rule["chamber_soak_tol_degC"], spread

    def run(self) -> None:
        s, ch, target, rule = self.s, self.ch, self.target, self.rule
        s.state = f"chamber to {target:g} degC"
        t0 = time.monotonic()
        t_end = t0 + rule["chamber_soak_timeout_s"]
        rate = ramp_limit(rule, self.prof)
        if not rule.get("chamber_soak", True):  # a ramp segment: set it going, record at once
            s.state = f"ramping to {target:g} degC"
            if not ch.motorised:
                lim = f" at {rate:g} degC/min" if rate else ""
                ch.ask(f"[{self.label}] start the chamber ramping to {target:g} degC{lim}, then "
                       "press Enter")
                return
            if rate and not ch.set_ramp(rate):
                raise InputError(_NO_RAMP.format(label=self.label), self.prof.path)
            ch.set_temp(target)
            return
        if not ch.motorised:
            lim = f" at no more than {rate:g} degC/min" if rate else ""
            ch.ask(f"[{self.label}] set the chamber to {target:g} degC{lim}, then press Enter"
                   + ("" if self.col is not None else " when the unit has soaked"))
            if self.col is None:
                return
            s.state = f"soaking at {target:g} degC"
            self._wait(t_end, air=None)
            return
        native = bool(rate) and ch.set_ramp(rate)
        software = bool(rate) and not native
        sp = ch.read_temp() if software else target
        ch.set_temp(target if not software else sp)
        t_last = time.monotonic()
        air = ch.read_temp()
        next_poll = t_last + POLL_S
        while True:
            rows = s.pump(0.02)
            self._take(rows)
            now = time.monotonic()
            if now >= next_poll:
                next_poll = now + POLL_S
                air = ch.read_temp()
                if self.col is None:
                    self.hist.append((now - t0, air))
                if software and sp != target:
                    step = rate / 60.0 * (now - t_last)
                    sp = target if abs(target - sp) <= step else sp + np.sign(target - sp) * step
                    ch.set_temp(sp)
                t_last = now
                s.state = f"{'ramping' if sp != target else 'soaking'} to {target:g} degC " \
                          f"(chamber {air:.2f})"
                if sp == target and abs(air - target) <= max(AIR_TOL,
                                                              rule["chamber_soak_tol_degC"]):
                    ok, _ = self._stable()
                    if ok:
                        return
            if now > t_end:
                self._timeout(air)

    def _wait(self, t_end, air) -> None:
        while True:
            self._take(self.s.pump(0.02))
            if self._stable()[0]:
                return
            if time.monotonic() > t_end:
                self._timeout(air)

    def _timeout(self, air) -> None:
        _, spread = self._stable()
        what = "" if air is None else f"; the chamber reads {air:.2f} degC"
        moved = (f"its temperature moved by {spread:.3g} degC over the last "
                 f"{self.rule['chamber_soak_s']:g} s (limit {self.rule['chamber_soak_tol_degC']:g})"
                 if np.isfinite(spread) else
                 f"less than chamber_soak_s = {self.rule['chamber_soak_s']:g} s of readings")
        raise InputError(
            f"segment {self.label!r}: the unit did not soak at {self.target:g} degC within "
            f"{self.rule['chamber_soak_timeout_s']:g} s (chamber_soak_timeout_s): {moved}"
            f"{what}", None)


def temp_column(session) -> int | None:
    """The column of the IMU's temperature in the rows Session.pump returns."""
    chans = list(session.prof.channels)
    return 2 + chans.index("temp") if "temp" in chans else None


def soak_segment(session, seg) -> None:
    """Called by Session.run_plan before a segment is recorded: set the
    chamber (if the segment gives a setpoint) and wait for the soak."""
    ch = getattr(session, "chamber", None)
    if ch is None or "chamber_temp_degC" not in seg.extra:
        return
    rule = soak_rule(session.plan, seg)
    Soak(session, ch, session.chamber_profile, float(seg.extra["chamber_temp_degC"]), rule,
         temp_column(session), seg.label).run()
