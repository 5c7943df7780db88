"""Device profiles (TOML, docs/acquisition.md): what a new sensor or table
needs, so that supporting one needs no Python.

An IMU profile says how bytes become samples in SI units: the transport, the
framing (binary, ASCII sentences, CAN messages), the fields with their
types, scale factors and units, the checksum, the sequence counter and the
time source. A turntable profile lists command templates and response
patterns. Loading validates everything and raises InputError naming the file.
"""

from __future__ import annotations

import re
import struct
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from calib_cli.acquire.checksum import Crc, crc_from_spec
from calib_cli.errors import InputError
from calib_cli.io.profiles import shipped_profiles

G0 = 9.80665
D2R = np.pi / 180.0

# unit of a field as the device sends it -> factor to SI
UNIT_FACTORS = {
    "m/s^2": 1.0, "m/s2": 1.0, "g": G0, "mg": G0 * 1e-3, "ug": G0 * 1e-6,
    "rad/s": 1.0, "mrad/s": 1e-3, "deg/s": D2R, "dps": D2R, "deg/h": D2R / 3600.0,
    "degc": 1.0, "c": 1.0, "s": 1.0, "ms": 1e-3, "us": 1e-6, "rad": 1.0, "deg": D2R,
    "": 1.0, "1": 1.0,
}

TYPES = {"u8": "B", "i8": "b", "u16": "H", "i16": "h", "u32": "I", "i32": "i",
         "u64": "Q", "i64": "q", "f32": "f", "f64": "d"}
ROLE_RE = re.compile(r"^(ax|ay|az|gx|gy|gz|a\d+|g\d+|temp)$")


@dataclass(frozen=True)
class Field:
    """One field of a frame: raw value * scale * unit factor = SI value."""

    name: str
    type: str = "f64"  # binary/CAN: a TYPES key; ASCII: parsed as a number
    scale: float = 1.0
    unit: str = ""
    offset: int | None = None  # CAN: byte offset in the message (default: packed in order)
    literal: str | None = None  # ASCII: the token must equal this text

    @property
    def factor(self) -> float:
        return self.scale * UNIT_FACTORS[self.unit.lower()]


@dataclass(frozen=True)
class Checksum:
    """kind: none | xor | additive | crc. ``covers``: which bytes it protects
    (binary: after_sync | all | payload). ``byte_order`` of the stored value."""

    kind: str = "none"
    crc: Crc | None = None
    width: int = 8
    byte_order: str = "little"
    covers: str = "after_sync"

    @property
    def nbytes(self) -> int:
        return 0 if self.kind == "none" else (self.width + 7) // 8

    def compute(self, data: bytes) -> int:
        if self.kind == "crc":
            return self.crc.compute(data)
        if self.kind == "xor":
            x = 0
            for b in data:
                x ^= b
            return x
        if self.kind == "additive":
            return sum(data) & ((1 << self.width) - 1)
        return 0


@dataclass(frozen=True)
class CanMessage:
    can_id: int
    extended: bool
    fields: tuple[Field, ...]
    checksum: Checksum  # over the bytes before it, stored in the last bytes
    length: int  # data bytes


@dataclass(frozen=True)
class ImuProfile:
    """A parsed IMU profile. ``channels``: the SI channel names in sample order
    (ax ay az gx gy gz, or a0..a{n-1} g0..g{n-1}), then temp when present."""

    name: str
    path: str
    format: str  # binary | ascii | can
    rate_hz: float
    transport: dict
    fields: tuple[Field, ...] = ()
    # binary
    sync: bytes = b""
    length_type: str | None = None  # None: fixed-size frames
    length_covers: str = "payload"  # payload | payload+checksum
    byte_order: str = "little"
    checksum: Checksum = Checksum()
    # ascii
    start: str = "$"
    separator: str = "*"
    terminator: str = "\r\n"
    delimiter: str = ","
    pattern: re.Pattern | None = None
    hex_digits: int = 2
    # can
    messages: tuple[CanMessage, ...] = ()
    # sequence counter and time
    seq_field: str | None = None
    seq_bits: int = 16
    time_source: str = "host"  # counter | sequence | host
    time_field: str | None = None
    time_scale: float = 1.0
    time_bits: int = 32
    channels: tuple[str, ...] = ()
    raw_text: str = ""

    @property
    def n_sensors(self) -> int:
        """Sensors per kind: 3 for a triad, n for a redundant unit."""
        return sum(1 for c in self.channels if c.startswith("a") and c != "temp")

    @property
    def redundant(self) -> bool:
        return "a0" in self.channels

    @property
    def has_temp(self) -> bool:
        return "temp" in self.channels

    def all_fields(self) -> tuple[Field, ...]:
        if self.format == "can":
            return tuple(f for m in self.messages for f in m.fields)
        return self.fields

    def payload_struct(self) -> struct.Struct:
        """Binary payload layout (fields in order, no padding)."""
        bo = "<" if self.byte_order == "little" else ">"
        return struct.Struct(bo + "".join(TYPES[f.type] for f in self.fields))

    @property
    def frame_size(self) -> int:
        """Binary: bytes in a whole frame (sync, length, payload, checksum)."""
        ln = struct.calcsize(TYPES[self.length_type]) if self.length_type else 0
        return len(self.sync) + ln + self.payload_struct().size + self.checksum.nbytes


def _fail(msg, path):
    raise InputError(msg, path)


def _field(raw: dict, where: str, path: str, binary: bool) -> Field:
    if not isinstance(raw, dict) or "name" not in raw:
        _fail(f"{where}: each field needs a name", path)
    typ = raw.get("type", "f64" if not binary else None)
    if binary and typ not in TYPES:
        _fail(f"{where} ({raw['name']!r}): type must be one of {', '.join(TYPES)}, got {typ!r}",
              path)
    unit = str(raw.get("unit", ""))
    if unit.lower() not in UNIT_FACTORS:
        _fail(f"{where} ({raw['name']!r}): unknown unit {unit!r}; known: "
              f"{', '.join(k for k in UNIT_FACTORS if k)}", path)
    try:
        scale = float(raw.get("scale", 1.0))
    except (TypeError, ValueError):
        _fail(f"{where} ({raw['name']!r}): scale must be a number", path)
    off = raw.get("offset")
    return Field(name=str(raw["name"]), type=typ or "f64", scale=scale, unit=unit,
                 offset=None if off is None else int(off), literal=raw.get("literal"))


def _checksum(raw, path, where="checksum") -> Checksum:
    if raw is None:
        return Checksum()
    if isinstance(raw, str):
        raw = {"kind": raw}
    kind = raw.get("kind", "none")
    if kind not in ("none", "xor", "additive", "crc"):
        _fail(f"{where}.kind must be none, xor, additive or crc, got {kind!r}", path)
    crc = None
    width = int(raw.get("width", 8))
    if kind == "crc":
        try:
            crc = crc_from_spec(raw, where)
        except ValueError as exc:
            _fail(str(exc), path)
        width = crc.width
    if kind == "xor":
        width = 8
    covers = raw.get("covers", "after_sync")
    if covers not in ("after_sync", "all", "payload"):
        _fail(f"{where}.covers must be after_sync, all or payload, got {covers!r}", path)
    bo = raw.get("byte_order", "little")
    if bo not in ("little", "big"):
        _fail(f"{where}.byte_order must be little or big", path)
    return Checksum(kind, crc, width, bo, covers)


def _channels(fields, path) -> tuple[str, ...]:
    names = [f.name for f in fields if ROLE_RE.match(f.name)]
    triad = [c for c in ("ax", "ay", "az", "gx", "gy", "gz") if c in names]
    acc = sorted((c for c in names if re.fullmatch(r"a\d+", c)), key=lambda c: int(c[1:]))
    gyr = sorted((c for c in names if re.fullmatch(r"g\d+", c)), key=lambda c: int(c[1:]))
    if triad and (acc or gyr):
        _fail("fields mix a triad (ax..gz) with redundant channels (a0.., g0..)", path)
    if triad:
        if len(triad) != 6:
            _fail(f"a triad profile needs fields ax ay az gx gy gz; has {', '.join(triad)}", path)
        out = triad
    else:
        n = len(acc)
        if n == 0 or acc != [f"a{i}" for i in range(n)] or gyr != [f"g{i}" for i in range(n)]:
            _fail("fields must name the channels ax ay az gx gy gz, or a0..a{n-1} and "
                  "g0..g{n-1}", path)
        out = acc + gyr
    if "temp" in names:
        out.append("temp")
    return tuple(out)


def parse_imu_profile(text: str, path: str = "<profile>") -> ImuProfile:
    """Parse and validate an IMU profile (strict keys and values: io/schema.py)."""
    from calib_cli.io import schema

    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        _fail(f"not valid TOML: {exc}", path)
    except RecursionError:
        _fail("not valid TOML: nested too deeply", path)
    schema.check_profile_keys(raw, schema.IMU_PROFILE, path)
    try:
        prof = _parse_imu_profile(raw, text, path)
    except (TypeError, ValueError, AttributeError, KeyError, OverflowError) as exc:
        raise InputError(f"malformed profile: {type(exc).__name__}: {exc}", path) from None
    schema.check_imu_profile_values(raw, prof, path)
    return prof


def _parse_imu_profile(raw: dict, text: str, path: str) -> ImuProfile:
    fmt = raw.get("format")
    if fmt not in ("binary", "ascii", "can"):
        _fail(f"format must be binary, ascii or can, got {fmt!r}", path)
    rate = raw.get("rate_hz")
    if not isinstance(rate, (int, float)) or rate <= 0:
        _fail("rate_hz (the nominal output rate) must be a positive number", path)
    transport = dict(raw.get("transport", {}))
    transport.setdefault("kind", "can" if fmt == "can" else "serial")
    frame = raw.get("frame", {})
    kw: dict = {}
    if fmt in ("binary", "ascii"):
        fields = tuple(_field(f, f"field {i + 1}", path, fmt == "binary")
                       for i, f in enumerate(raw.get("field", [])))
        if not fields:
            _fail("no [[field]] entries", path)
        kw["fields"] = fields
    if fmt == "binary":
        sync = frame.get("sync", "")
        try:
            kw["sync"] = bytes.fromhex(sync)
        except ValueError:
            _fail(f"frame.sync must be hex bytes like \"AA 55\", got {sync!r}", path)
        if not kw["sync"]:
            _fail("frame.sync: a binary profile needs sync bytes to resynchronise", path)
        lt = frame.get("length_type")
        if lt is not None and lt not in ("u8", "u16"):
            _fail("frame.length_type must be u8 or u16 (or absent for fixed-size frames)", path)
        kw["length_type"] = lt
        kw["length_covers"] = frame.get("length_covers", "payload")
        kw["byte_order"] = frame.get("byte_order", "little")
        if kw["byte_order"] not in ("little", "big"):
            _fail("frame.byte_order must be little or big", path)
        kw["checksum"] = _checksum(raw.get("checksum"), path)
    elif fmt == "ascii":
        kw["start"] = frame.get("start", "$")
        kw["terminator"] = frame.get("terminator", "\r\n")
        kw["delimiter"] = frame.get("delimiter", ",")
        cs = raw.get("checksum", {"kind": "none"})
        cs = {"kind": cs} if isinstance(cs, str) else cs
        kw["separator"] = cs.get("separator", "*")
        kw["hex_digits"] = int(cs.get("hex_digits", 2))
        kw["checksum"] = _checksum({k: v for k, v in cs.items()
                                    if k not in ("separator", "hex_digits")}, path)
        if "pattern" in frame:
            try:
                kw["pattern"] = re.compile(frame["pattern"])
            except re.error as exc:
                _fail(f"frame.pattern is not a valid regular expression: {exc}", path)
            missing = [f.name for f in kw["fields"] if f.literal is None
                       and f.name not in kw["pattern"].groupindex]
            if missing:
                _fail(f"frame.pattern lacks named groups for {', '.join(missing)}", path)
    else:
        msgs = []
        for i, m in enumerate(raw.get("message", [])):
            where = f"message {i + 1}"
            if "id" not in m:
                _fail(f"{where}: needs an arbitration id", path)
            flds = tuple(_field(f, f"{where} field {j + 1}", path, True)
                         for j, f in enumerate(m.get("field", [])))
            bo = "<" if m.get("byte_order", raw.get("byte_order", "little")) == "little" else ">"
            pos, placed = 0, []
            for f in flds:
                off = pos if f.offset is None else f.offset
                placed.append(Field(f.name, f.type, f.scale, f.unit, off))
                pos = off + struct.calcsize(bo + TYPES[f.type])
            cs = _checksum(m.get("checksum"), path, f"{where}.checksum")
            length = int(m.get("length", pos + cs.nbytes))
            if length > 8 or pos + cs.nbytes > length:
                _fail(f"{where}: fields and checksum need {pos + cs.nbytes} bytes; a classic "
                      "CAN frame holds 8", path)
            msgs.append(CanMessage(int(m["id"]), bool(m.get("extended", False)),
                                   tuple(placed), cs, length))
        if not msgs:
            _fail("a CAN profile needs [[message]] entries", path)
        kw["messages"] = tuple(msgs)
        kw["byte_order"] = raw.get("byte_order", "little")
    all_fields = kw.get("fields") or tuple(f for m in kw["messages"] for f in m.fields)
    names = [f.name for f in all_fields]
    seq = raw.get("sequence", {})
    if seq:
        if seq.get("field") not in names:
            _fail(f"sequence.field {seq.get('field')!r} is not a field", path)
        kw["seq_field"] = seq["field"]
        kw["seq_bits"] = int(seq.get("bits", 16))
    if fmt == "can":
        if not kw.get("seq_field"):
            _fail("a CAN profile needs [sequence] field: the counter that ties the messages "
                  "of one sample together", path)
        for m in kw["messages"]:
            if kw["seq_field"] not in [f.name for f in m.fields]:
                _fail(f"message 0x{m.can_id:X} lacks the counter field {kw['seq_field']!r}", path)
    ts = raw.get("timestamp", {"source": "sequence" if seq else "host"})
    src = ts.get("source", "host")
    if src not in ("counter", "sequence", "host"):
        _fail(f"timestamp.source must be counter, sequence or host, got {src!r}", path)
    if src == "sequence" and not seq:
        _fail("timestamp.source = \"sequence\" needs a [sequence] counter", path)
    kw["time_source"] = src
    if src == "counter":
        if ts.get("field") not in names:
            _fail(f"timestamp.field {ts.get('field')!r} is not a field", path)
        kw["time_field"] = ts["field"]
        kw["time_scale"] = float(ts.get("scale", 1.0)) * UNIT_FACTORS[str(ts.get("unit", "s"))
                                                                      .lower()]
        kw["time_bits"] = int(ts.get("bits", 32))
    kw["channels"] = _channels(all_fields, path)
    return ImuProfile(name=str(raw.get("name", Path(path).stem)), path=path, format=fmt,
                      rate_hz=float(rate), transport=transport, raw_text=text, **kw)


def _read(path) -> str:
    p = str(path)
    try:
        return Path(p).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError("no such file", p) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read profile: {exc}", p) from None


PROFILE_DIR = shipped_profiles()


def resolve_profile(name: str, kind: str) -> str:
    """A profile path, or the name of a shipped profile (profiles/KIND/NAME.toml)."""
    p = Path(name)
    if p.exists() or p.suffix == ".toml" or "/" in name:
        return str(p)
    from calib_cli.io.profiles import find_profile

    found = find_profile(name, kind)  # $CALIB_PROFILE_PATH, ~/.config/calib/profiles, shipped
    return str(found or PROFILE_DIR / kind / f"{name}.toml")


def _read_named(name: str, p: str, kind: str) -> str:
    """The profile text; an unknown shipped name lists the shipped profiles."""
    try:
        return _read(p)
    except InputError as exc:
        if exc.message == "no such file" and str(p) != str(name):
            shipped = sorted(x.stem for x in (PROFILE_DIR / kind).glob("*.toml"))
            raise InputError(f"no {kind} profile named {name!r}; shipped: "
                             f"{', '.join(shipped) or 'none'} (or give a .toml path)",
                             name) from None
        raise


def load_imu_profile(path) -> ImuProfile:
    p = resolve_profile(str(path), "imu")
    return parse_imu_profile(_read_named(str(path), p, "imu"), p)


# ---------------------------------------------------------------------------
# turntables

TABLE_COMMANDS = ("move", "rate", "stop", "query_angle", "query_status")


@dataclass(frozen=True)
class TableProfile:
    """Command templates use Python format fields: {roll_deg} {pitch_deg}
    {yaw_deg} (move), {rate_dps} (rate). Responses are regular expressions
    with named groups: angle -> roll_deg/pitch_deg/yaw_deg, status -> state."""

    name: str
    path: str
    kind: str  # serial | manual
    transport: dict = field(default_factory=dict)
    commands: dict = field(default_factory=dict)
    responses: dict = field(default_factory=dict)
    replies: dict = field(default_factory=dict)  # for the emulator: reply templates
    settled_states: tuple[str, ...] = ("IDLE",)
    terminator: str = "\r\n"
    timeout_s: float = 60.0
    speed_dps: float = 90.0  # the emulator's slew speed
    axes: tuple[str, ...] = ("roll", "pitch", "yaw")

    def format(self, name: str, **values) -> bytes:
        return self.commands[name].format(**values).encode()


def _template_axes(tpl: str) -> tuple[str, ...]:
    return tuple(a for a in ("roll", "pitch", "yaw") if "{" + a + "_deg" in tpl)


def parse_table_profile(text: str, path: str = "<table>") -> TableProfile:
    """Parse and validate a turntable profile (strict keys, templates: io/schema.py)."""
    from calib_cli.io import schema

    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        _fail(f"not valid TOML: {exc}", path)
    except RecursionError:
        _fail("not valid TOML: nested too deeply", path)
    schema.check_profile_keys(raw, schema.TABLE_PROFILE, path)
    if isinstance(raw.get("commands"), dict):
        schema.check_table_templates(raw["commands"], path)
    if "transport" in raw:
        schema.check_transport(raw["transport"], path)
    try:
        return _parse_table_profile(raw, text, path)
    except (TypeError, ValueError, AttributeError, KeyError, OverflowError) as exc:
        raise InputError(f"malformed profile: {type(exc).__name__}: {exc}", path) from None


def _parse_table_profile(raw: dict, text: str, path: str) -> TableProfile:
    kind = raw.get("kind", "serial")
    if kind not in ("serial", "manual"):
        _fail(f"kind must be serial or manual, got {kind!r}", path)
    name = str(raw.get("name", Path(path).stem))
    if kind == "manual":
        return TableProfile(name=name, path=path, kind="manual")
    cmds = raw.get("commands", {})
    for c in ("move", "query_status"):
        if c not in cmds:
            _fail(f"[commands] needs {c!r}", path)
    unknown = set(cmds) - set(TABLE_COMMANDS)
    if unknown:
        _fail(f"unknown commands {', '.join(sorted(unknown))}; known: "
              f"{', '.join(TABLE_COMMANDS)}", path)
    resp = {}
    for k, v in raw.get("responses", {}).items():
        if k == "settled":
            continue
        try:
            resp[k] = re.compile(v)
        except re.error as exc:
            _fail(f"responses.{k} is not a valid regular expression: {exc}", path)
    if "status" not in resp or "state" not in resp["status"].groupindex:
        _fail("responses.status must be a pattern with a named group (?P<state>...)", path)
    settled = raw.get("responses", {}).get("settled", ["IDLE"])
    settled = (settled,) if isinstance(settled, str) else tuple(settled)
    axes = _template_axes(cmds["move"])
    if not axes:
        _fail("commands.move must use {roll_deg}, {pitch_deg} and/or {yaw_deg}", path)
    return TableProfile(name=name, path=path, kind="serial", transport=raw.get("transport", {}),
                        commands=dict(cmds), responses=resp, replies=raw.get("replies", {}),
                        settled_states=settled, terminator=raw.get("terminator", "\r\n"),
                        timeout_s=float(raw.get("timeout_s", 60.0)),
                        speed_dps=float(raw.get("speed_dps", 90.0)), axes=axes)


def load_table_profile(path) -> TableProfile:
    if str(path) == "manual":
        return TableProfile(name="manual", path="manual", kind="manual")
    p = resolve_profile(str(path), "turntable")
    return parse_table_profile(_read_named(str(path), p, "turntable"), p)
