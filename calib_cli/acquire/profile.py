"""Device profiles (TOML, docs/acquisition.md): what a new sensor or table
needs, so that supporting one needs no Python.

An IMU profile says how bytes become samples in SI units: the transport, the
framing (binary, ASCII sentences, CAN messages), the fields with their
types, scale factors and units, the checksum, the sequence counter and the
time source. A turntable profile lists command templates and response
patterns. Loading validates everything and raises InputError naming the file.
"""

from __future__ import annotations

import dataclasses
import re
import struct
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from calib_cli.acquire.checksum import Crc, crc_from_spec
from calib_cli.acquire.typed import Typed
from calib_cli.errors import InputError
from calib_cli.io.profiles import shipped_profiles

G0 = 9.80665
D2R = np.pi / 180.0

# unit of a field as the device sends it -> factor to SI
UNIT_FACTORS = {
    "m/s^2": 1.0, "m/s2": 1.0, "g": G0, "mg": G0 * 1e-3, "ug": G0 * 1e-6,
    "rad/s": 1.0, "mrad/s": 1e-3, "deg/s": D2R, "dps": D2R, "deg/h": D2R / 3600.0,
    "degc": 1.0, "c": 1.0, "s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9, "rad": 1.0,
    "deg": D2R, "": 1.0, "1": 1.0,
}

# binary field types: struct code (None: 24-bit, decoded apart) and size in bytes
TYPES = {"u8": "B", "i8": "b", "u16": "H", "i16": "h", "u24": None, "i24": None,
         "u32": "I", "i32": "i", "u64": "Q", "i64": "q", "f32": "f", "f64": "d"}
TYPE_SIZE = {"u8": 1, "i8": 1, "u16": 2, "i16": 2, "u24": 3, "i24": 3, "u32": 4, "i32": 4,
             "u64": 8, "i64": 8, "f32": 4, "f64": 8}
ROLE_RE = re.compile(r"^(ax|ay|az|gx|gy|gz|a\d+|g\d+|temp)$")
MAX_FIELDS = 512  # fields of one profile (a frame of 1000 fields is refused, issue 37)
MAX_FRAME = 4096  # bytes of one binary frame
MAX_RATE_HZ = 100_000.0
PLACEHOLDER_RE = re.compile(r"\{(rate|div|code)(?::(u8|u16be|u16le|u32be|u32le|f32be|f32le))?\}")


@dataclass(frozen=True)
class Field:
    """One field of a frame: SI value = (raw * scale + add) * unit factor."""

    name: str
    type: str = "f64"  # binary/CAN: a TYPES key; ASCII: parsed as a number
    scale: float = 1.0
    unit: str = ""
    offset: int | None = None  # CAN: byte offset in the message; tagged: offset in the record
    literal: str | None = None  # ASCII: the token must equal this text
    add: float = 0.0  # added after scaling, in the field's unit (a temperature's zero point)
    tag: int | None = None  # tagged payloads: the identifier of the record carrying it
    group: int | None = None  # group-bitmask headers (VectorNav): the group ...
    bit: int | None = None  # ... and the bit of the output that carries it
    optional: bool = False  # may be missing from a frame: the last value is held

    @property
    def unit_factor(self) -> float:
        return UNIT_FACTORS[self.unit.lower()]

    @property
    def factor(self) -> float:
        return self.scale * self.unit_factor


@dataclass(frozen=True)
class Checksum:
    """kind: none | xor | additive | fletcher | crc. ``covers``: which bytes it
    protects (binary: after_sync | all | payload, or an integer: the frame bytes
    from that offset). ``byte_order`` of the stored value. additive: sum of
    ``word``-byte words (``word_order``) mod 2**width, ``negate``: the two's
    complement (the frame sums to zero, Xsens Xbus). fletcher: the two running
    sums mod ``modulus`` (256 in MIP, 255 in Fletcher-16), stored sum1 then sum2.
    crc: ``pad_to``: zero bytes appended to a multiple of it first (STIM300)."""

    kind: str = "none"
    crc: Crc | None = None
    width: int = 8
    byte_order: str = "little"
    covers: str | int = "after_sync"
    negate: bool = False
    modulus: int = 256
    word: int = 1
    word_order: str = "big"
    pad_to: int = 1

    @property
    def nbytes(self) -> int:
        return 0 if self.kind == "none" else (self.width + 7) // 8

    def compute(self, data: bytes) -> int:
        if self.pad_to > 1 and len(data) % self.pad_to:
            data = bytes(data) + bytes(self.pad_to - len(data) % self.pad_to)
        if self.kind == "crc":
            return self.crc.compute(data)
        if self.kind == "xor":
            x = 0
            for b in data:
                x ^= b
            return x
        mask = (1 << self.width) - 1
        if self.kind == "additive":
            if self.word == 1:
                s = sum(data)
            else:
                w = self.word
                s = sum(int.from_bytes(data[i:i + w], self.word_order)
                        for i in range(0, len(data), w))
            return (-s if self.negate else s) & mask
        if self.kind == "fletcher":
            s1 = s2 = 0
            m = self.modulus
            for b in data:
                s1 = (s1 + b) % m
                s2 = (s2 + s1) % m
            return (s1 << 8) | s2
        return 0

    def start(self, sync_len: int, header_len: int) -> int:
        """The first byte of a frame that the checksum covers (it ends at the
        checksum)."""
        if isinstance(self.covers, int):
            return self.covers
        return {"all": 0, "after_sync": sync_len, "payload": header_len}[self.covers]


@dataclass(frozen=True)
class Tagged:
    """A payload of records ``id | length | data`` (Xsens MTData2: u16 id, u8
    length of the data) or ``length | id | data`` (MIP: u8 length of the whole
    record, u8 descriptor)."""

    id_type: str = "u16"
    length_type: str = "u8"
    order: str = "id-length"
    length_includes_header: bool = False
    byte_order: str = "big"

    @property
    def header_size(self) -> int:
        return TYPE_SIZE[self.id_type] + TYPE_SIZE[self.length_type]


@dataclass(frozen=True)
class Layout:
    """One kind of binary frame: sync | [length] | payload | checksum | end.
    ``sync`` includes any fixed header (a message id, a group bitmask header)."""

    sync: bytes
    fields: tuple[Field, ...]
    length_type: str | None = None
    length_order: str = "little"
    length_covers: str = "payload"  # payload | payload+checksum
    tagged: Tagged | None = None
    end: bytes = b""
    name: str = ""

    @property
    def payload_size(self) -> int:
        """Bytes of a fixed payload (tagged: of the records it needs)."""
        if self.tagged is None:
            return sum(TYPE_SIZE[f.type] for f in self.fields)
        return sum(self.tagged.header_size + size for size in self.tag_sizes().values())

    def tag_sizes(self) -> dict[int, int]:
        """Tagged: data bytes of each record (fields packed in order, or by offset)."""
        out: dict[int, int] = {}
        for f in self.fields:
            off = f.offset if f.offset is not None else out.get(f.tag, 0)
            out[f.tag] = max(out.get(f.tag, 0), off + TYPE_SIZE[f.type])
        return out


@dataclass(frozen=True)
class CanMessage:
    can_id: int
    extended: bool
    fields: tuple[Field, ...]
    checksum: Checksum  # over the bytes before it, stored in the last bytes
    length: int  # data bytes
    dbc_name: str | None = None  # decoded by cantools from the profile's DBC file


@dataclass(frozen=True)
class Step:
    """One exchange of a configuration sequence: send a command, wait for the
    expected reply (``timeout_s``, ``retries``). Templates: hex bytes or text
    with placeholders {rate} {div} {code} (binary: {rate:u16be} ...).
    ``checksum``: none | frame (the profile's frame checksum, binary) | nmea
    (``*XX`` and CR LF after the text). ``readback``: the reply is kept under this
    name in raw.h5. ``reply``: what the emulator answers (default: ``expect``)."""

    send: str
    text: bool
    checksum: str = "none"
    expect: str | None = None
    timeout_s: float = 1.0
    retries: int = 2
    delay_s: float = 0.0
    readback: str | None = None
    reply: str | None = None
    description: str = ""


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
    layouts: tuple[Layout, ...] = ()
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
    dbc: object = None  # a cantools Database
    # sequence counter and time
    seq_field: str | None = None
    seq_bits: int = 16
    seq_modulus: float = 65536
    seq_per_s: float | None = None  # counts per second (a clock counter), else 1 a frame
    time_source: str = "host"  # counter | sequence | host
    time_field: str | None = None
    time_scale: float = 1.0
    time_bits: int = 32
    time_modulus: float = 2.0**32
    channels: tuple[str, ...] = ()
    raw_text: str = ""
    # configuration exchange (docs/acquisition.md)
    base_rate_hz: float | None = None
    rate_codes: dict = field(default_factory=dict)
    configure: tuple[Step, ...] = ()
    start_steps: tuple[Step, ...] = ()
    stop_steps: tuple[Step, ...] = ()
    identify: tuple[Step, ...] = ()
    document: str = ""

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

    @property
    def sync(self) -> bytes:
        return self.layouts[0].sync if self.layouts else b""

    @property
    def frame_size(self) -> int:
        """Binary: bytes in a whole frame of the first layout."""
        lay = self.layouts[0]
        ln = TYPE_SIZE[lay.length_type] if lay.length_type else 0
        return len(lay.sync) + ln + lay.payload_size + self.checksum.nbytes + len(lay.end)

    @property
    def seq_per_frame(self) -> float:
        return self.seq_per_s / self.rate_hz if self.seq_per_s else 1.0

    def with_rate(self, rate_hz: float) -> "ImuProfile":
        import dataclasses

        return dataclasses.replace(self, rate_hz=float(rate_hz))


def _fail(msg, path):
    raise InputError(msg, path)


FIELD_KEYS = {"name", "type", "unit", "scale", "offset", "literal", "add", "tag", "group",
              "bit", "optional", "signal"}
STEP_KEYS = {"send", "send_text", "expect", "expect_text", "checksum", "timeout_s", "retries",
             "delay_s", "readback", "reply", "reply_text", "description"}
CHECKSUM_KEYS = {"kind", "name", "width", "poly", "init", "refin", "refout", "xorout",
                 "covers", "byte_order", "separator", "hex_digits", "negate", "modulus", "word",
                 "pad_to"}
IMU_KEYS = {
    "": {"name", "description", "document", "format", "rate_hz", "base_rate_hz", "rate_codes",
         "transport", "frame", "checksum", "sequence", "timestamp", "field", "byte_order",
         "message", "noise", "datagram", "configure", "start", "stop", "identify", "dbc"},
    "transport": {"kind", "baudrate", "bytesize", "parity", "stopbits", "interface", "channel",
                  "bitrate", "timeout_s"},
    "frame": {"sync", "length_type", "length_covers", "length_byte_order", "byte_order",
              "start", "terminator", "delimiter", "pattern", "end", "tagged", "groups"},
    "tagged": {"id_type", "length_type", "order", "length_includes_header", "byte_order"},
    "sequence": {"field", "bits", "modulus", "counts_per_s"},
    "timestamp": {"source", "field", "scale", "unit", "bits", "modulus"},
    "message": {"id", "extended", "field", "checksum", "length", "byte_order", "name"},
    "datagram": {"id", "field", "description"},
    "noise": {"accel_std", "gyro_std", "accel_white", "gyro_white"},
}


def _field(t: Typed, raw: dict, where: str, binary: bool) -> Field:
    t.keys(raw, FIELD_KEYS, f"{where}: ")
    name = t.text(raw, "name", f"{where}: ", allow_empty=False)
    w = f"{where} ({name!r}): "
    typ = t.text(raw, "type", w, default=None)
    if binary and typ not in TYPES:
        t.fail(f"{w}type must be one of {', '.join(TYPES)}, got {typ!r}")
    unit = t.text(raw, "unit", w, default="")
    if unit.lower() not in UNIT_FACTORS:
        t.fail(f"{w}unknown unit {unit!r}; known: {', '.join(k for k in UNIT_FACTORS if k)}")
    scale = t.num(raw, "scale", w, default=1.0)
    if scale == 0:
        t.fail(f"{w}scale must be a finite non-zero number, got {scale!r}")
    def opt_int(key, hi):
        return t.num(raw, key, w, default=None, lo=0, hi=hi, integer=True)
    return Field(name=name, type=typ or "f64", scale=float(scale), unit=unit,
                 offset=opt_int("offset", MAX_FRAME), literal=t.text(raw, "literal", w, None),
                 add=float(t.num(raw, "add", w, default=0.0)), tag=opt_int("tag", 0xFFFF),
                 group=t.num(raw, "group", w, default=None, lo=1, hi=8, integer=True),
                 bit=opt_int("bit", 15), optional=t.flag(raw, "optional", w))


def _checksum(t: Typed, raw, where: str = "checksum", ascii_keys: bool = False) -> Checksum:
    if raw is None:
        return Checksum()
    if isinstance(raw, str):
        raw = {"kind": raw}
    if not isinstance(raw, dict):
        t.fail(f"{where} must be a table")
    t.keys(raw, CHECKSUM_KEYS, f"[{where}] ")
    w = f"{where}."
    kind = t.text(raw, "kind", w, "none", ("none", "xor", "additive", "fletcher", "crc"))
    crc = None
    width = int(t.num(raw, "width", w, 8 if kind != "fletcher" else 16, lo=8, hi=64,
                      integer=True))
    if kind == "crc":
        for k in ("poly", "init", "xorout"):
            t.num(raw, k, w, default=0, lo=0, hi=2**64 - 1, integer=True)
        for k in ("refin", "refout"):
            t.flag(raw, k, w)
        if "name" in raw:
            t.text(raw, "name", w)
        try:
            crc = crc_from_spec(raw, where)
        except ValueError as exc:
            t.fail(str(exc))
        width = crc.width
    if kind == "xor":
        width = 8
    if kind == "fletcher" and width != 16:
        t.fail(f"{w}width: a Fletcher checksum here is 16 bits")
    covers = raw.get("covers", "after_sync")
    if isinstance(covers, str):
        t.text(raw, "covers", w, "after_sync", ("after_sync", "all", "payload"))
    else:
        covers = int(t.num(raw, "covers", w, lo=0, hi=MAX_FRAME, integer=True))
    return Checksum(kind, crc, width, t.text(raw, "byte_order", w, "little", ("little", "big")),
                    covers, t.flag(raw, "negate", w),
                    int(t.num(raw, "modulus", w, 256, lo=2, hi=65536, integer=True)),
                    int(t.num(raw, "word", w, 1, lo=1, hi=8, integer=True)),
                    "big", int(t.num(raw, "pad_to", w, 1, lo=1, hi=16, integer=True)))


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
    """Parse and validate an IMU profile: strict keys, typed finite values (a
    number is a number, not a bool or a string); one InputError naming the file
    and the key."""
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        _fail(f"not valid TOML: {exc}", path)
    except RecursionError:
        _fail("not valid TOML: nested too deeply", path)
    t = Typed(path)
    t.keys(raw, IMU_KEYS[""])
    for name in ("transport", "frame", "sequence", "timestamp", "noise"):
        t.keys(t.table(raw, name), IMU_KEYS[name], f"[{name}] ")
    try:
        return _parse_imu_profile(raw, text, path, t)
    except (TypeError, ValueError, AttributeError, KeyError, OverflowError) as exc:
        raise InputError(f"malformed profile: {type(exc).__name__}: {exc}", path) from None


def _group_header(t: Typed, fields, where: str) -> tuple[bytes, tuple[Field, ...]]:
    """VectorNav-style header after the sync byte: a byte of group bits, then
    one little-endian u16 field mask per group present; the payload holds the
    outputs in group then bit order."""
    if any(f.group is None or f.bit is None for f in fields):
        t.fail(f"{where}: frame.groups = true needs group and bit on every field")
    groups = sorted({f.group for f in fields})
    head = bytes([sum(1 << (g - 1) for g in groups)])
    for g in groups:
        head += sum(1 << b for b in {f.bit for f in fields if f.group == g}).to_bytes(2, "little")
    order = sorted(range(len(fields)), key=lambda i: (fields[i].group, fields[i].bit, i))
    return head, tuple(fields[i] for i in order)


def _layout(t: Typed, frame: dict, fields, sync: bytes, where: str, byte_order: str) -> Layout:
    lt = t.text(frame, "length_type", "frame.", None, ("u8", "u16"))
    tagged = None
    if "tagged" in frame:
        tg = t.table(frame, "tagged", "frame.")
        t.keys(tg, IMU_KEYS["tagged"], "[frame.tagged] ")
        tagged = Tagged(t.text(tg, "id_type", "frame.tagged.", "u16", ("u8", "u16")),
                        t.text(tg, "length_type", "frame.tagged.", "u8", ("u8", "u16")),
                        t.text(tg, "order", "frame.tagged.", "id-length",
                               ("id-length", "length-id")),
                        t.flag(tg, "length_includes_header", "frame.tagged."),
                        t.text(tg, "byte_order", "frame.tagged.", "big", ("little", "big")))
        if lt is None:
            t.fail("frame.tagged needs frame.length_type: the frame says how long it is")
        missing = [f.name for f in fields if f.tag is None]
        if missing:
            t.fail(f"{where}: a tagged payload needs tag on every field; lacking: "
                   f"{', '.join(missing)}")
    if tagged is not None:  # each field's offset in its record (packed in order by default)
        pos: dict[int, int] = {}
        placed = []
        for f in fields:
            off = f.offset if f.offset is not None else pos.get(f.tag, 0)
            pos[f.tag] = off + TYPE_SIZE[f.type]
            placed.append(dataclasses.replace(f, offset=off))
        fields = tuple(placed)
    if t.flag(frame, "groups", "frame."):
        head, fields = _group_header(t, fields, where)
        sync = sync + head
    lay = Layout(sync=sync, fields=tuple(fields), length_type=lt,
                 length_order=t.text(frame, "length_byte_order", "frame.", byte_order,
                                     ("little", "big")),
                 length_covers=t.text(frame, "length_covers", "frame.", "payload",
                                      ("payload", "payload+checksum")),
                 tagged=tagged, end=t.hexbytes(frame, "end", "frame.", b""),
                 name=where)
    size = lay.payload_size + len(sync) + 16
    if size > MAX_FRAME or (lt == "u8" and lay.payload_size > 255):
        t.fail(f"{where}: the payload of {lay.payload_size} bytes does not fit "
               f"{'a u8 length' if lt == 'u8' and size <= MAX_FRAME else f'{MAX_FRAME} bytes'}")
    return lay


def _fields(t: Typed, table: dict, where: str, binary: bool) -> tuple[Field, ...]:
    raw = t.tables(table, "field", limit=MAX_FIELDS)
    fields = tuple(_field(t, f, f"{where}field {i + 1}", binary) for i, f in enumerate(raw))
    if not fields:
        t.fail(f"{where}no [[field]] entries")
    return fields


def _steps(t: Typed, raw: dict, key: str, binary: bool) -> tuple[Step, ...]:
    out = []
    for i, s in enumerate(t.tables(raw, key, limit=64)):
        w = f"{key} {i + 1}: "
        t.keys(s, STEP_KEYS, w)
        text = "send_text" in s
        if text == ("send" in s):
            t.fail(f"{w}give send (hex bytes) or send_text (text)")
        send = t.text(s, "send_text" if text else "send", w, allow_empty=False)
        ex_key, rep_key = ("expect_text", "reply_text") if text else ("expect", "reply")
        for k in (("expect", "reply") if text else ("expect_text", "reply_text")):
            if k in s:
                t.fail(f"{w}{k} does not go with {'send_text' if text else 'send'}")
        step = Step(send=send, text=text,
                    checksum=t.text(s, "checksum", w, "none", ("none", "frame", "nmea")),
                    expect=t.text(s, ex_key, w, None), reply=t.text(s, rep_key, w, None),
                    timeout_s=float(t.num(s, "timeout_s", w, 1.0, lo=0, hi=600, lo_open=True)),
                    retries=int(t.num(s, "retries", w, 2, lo=0, hi=20, integer=True)),
                    delay_s=float(t.num(s, "delay_s", w, 0.0, lo=0, hi=60)),
                    readback=t.text(s, "readback", w, None),
                    description=t.text(s, "description", w, ""))
        from calib_cli.acquire.device import check_template

        for tpl in (step.send, step.expect, step.reply):
            if tpl is not None:
                msg = check_template(tpl, step.text)
                if msg:
                    t.fail(f"{w}{msg}")
        if step.checksum == "frame" and not binary:
            t.fail(f"{w}checksum = \"frame\" needs a binary profile (use \"nmea\")")
        out.append(step)
    return tuple(out)


def _parse_imu_profile(raw: dict, text: str, path: str, t: Typed) -> ImuProfile:
    fmt = t.text(raw, "format", "", None)
    if fmt not in ("binary", "ascii", "can"):
        _fail(f"format must be binary, ascii or can, got {fmt!r}", path)
    rate = t.num(raw, "rate_hz", "", lo=0, hi=MAX_RATE_HZ, lo_open=True)
    t.text(raw, "name", "", "")
    t.text(raw, "description", "", "")
    transport = dict(t.table(raw, "transport"))
    from calib_cli.io.schema import check_transport

    check_transport(transport, path)
    transport.setdefault("kind", "can" if fmt == "can" else "serial")
    frame = t.table(raw, "frame")
    byte_order = t.text(frame, "byte_order", "frame.", t.text(raw, "byte_order", "", "little"),
                        ("little", "big"))
    kw: dict = {"byte_order": byte_order}
    if fmt in ("binary", "ascii"):
        datagrams = t.tables(raw, "datagram", limit=64)
        if fmt == "ascii" or not datagrams:
            kw["fields"] = _fields(t, raw, "", fmt == "binary")
    if fmt == "binary":
        sync = t.hexbytes(frame, "sync", "frame.", b"")
        kw["checksum"] = _checksum(t, raw.get("checksum"))
        if datagrams:  # the identifier byte(s) decide the content (STIM300)
            if "field" in raw:
                t.fail("give [[field]] or [[datagram]] entries, not both")
            lays, union = [], {}
            for i, d in enumerate(datagrams):
                w = f"datagram {i + 1}"
                t.keys(d, IMU_KEYS["datagram"], f"{w}: ")
                flds = _fields(t, d, f"{w} ", True)
                ident = t.hexbytes(d, "id", f"{w}: ")
                lays.append(dataclasses.replace(
                    _layout(t, frame, flds, sync + ident, w, byte_order),
                    name=ident.hex().upper()))
                for f in flds:
                    union.setdefault(f.name, f)
            kw["layouts"] = tuple(lays)
            kw["fields"] = tuple(union.values())
        else:
            lay = _layout(t, frame, kw["fields"], sync, "frame", byte_order)
            kw["layouts"] = (lay,)
            kw["fields"] = lay.fields
        if not any(lay.sync for lay in kw["layouts"]):
            _fail("frame.sync: a binary profile needs sync bytes to resynchronise", path)
    elif fmt == "ascii":
        kw["start"] = t.text(frame, "start", "frame.", "$", allow_empty=False)
        kw["terminator"] = t.text(frame, "terminator", "frame.", "\r\n", allow_empty=False)
        kw["delimiter"] = t.text(frame, "delimiter", "frame.", ",", allow_empty=False)
        cs = raw.get("checksum", {"kind": "none"})
        cs = {"kind": cs} if isinstance(cs, str) else cs
        if not isinstance(cs, dict):
            t.fail("[checksum] must be a table")
        kw["separator"] = t.text(cs, "separator", "checksum.", "*", allow_empty=False)
        kw["hex_digits"] = int(t.num(cs, "hex_digits", "checksum.", 2, lo=1, hi=8,
                                     integer=True))
        kw["checksum"] = _checksum(t, {k: v for k, v in cs.items()
                                       if k not in ("separator", "hex_digits")})
        if "pattern" in frame:
            try:
                kw["pattern"] = re.compile(t.text(frame, "pattern", "frame."))
            except re.error as exc:
                _fail(f"frame.pattern is not a valid regular expression: {exc}", path)
            missing = [f.name for f in kw["fields"] if f.literal is None
                       and f.name not in kw["pattern"].groupindex]
            if missing:
                _fail(f"frame.pattern lacks named groups for {', '.join(missing)}", path)
    else:
        kw["messages"], kw["dbc"] = _can_messages(t, raw, path, byte_order)
    all_fields = kw.get("fields") or tuple(f for m in kw["messages"] for f in m.fields)
    if len(all_fields) > MAX_FIELDS:
        t.fail(f"{len(all_fields)} fields; at most {MAX_FIELDS}")
    names = [f.name for f in all_fields]
    seq = t.table(raw, "sequence")
    if seq:
        sf = t.text(seq, "field", "sequence.")
        if sf not in names:
            _fail(f"sequence.field {sf!r} is not a field", path)
        kw["seq_field"] = sf
        bits = t.num(seq, "bits", "sequence.", 16, lo=1, hi=64, integer=True)
        kw["seq_bits"] = int(bits)
        kw["seq_modulus"] = t.num(seq, "modulus", "sequence.", float(2 ** int(bits)), lo=1,
                                  lo_open=False)
        kw["seq_per_s"] = t.num(seq, "counts_per_s", "sequence.", None, lo=0, lo_open=True)
    if fmt == "can":
        for m in kw["messages"]:
            if kw.get("seq_field") and kw["seq_field"] not in [f.name for f in m.fields]:
                _fail(f"message 0x{m.can_id:X} lacks the counter field {kw['seq_field']!r}", path)
    ts = t.table(raw, "timestamp", default={"source": "sequence" if seq else "host"})
    src = t.text(ts, "source", "timestamp.", "host", ("counter", "sequence", "host"))
    if src == "sequence" and not seq:
        _fail("timestamp.source = \"sequence\" needs a [sequence] counter", path)
    kw["time_source"] = src
    if src == "counter":
        tf = t.text(ts, "field", "timestamp.")
        if tf not in names:
            _fail(f"timestamp.field {tf!r} is not a field", path)
        kw["time_field"] = tf
        unit = t.text(ts, "unit", "timestamp.", "s")
        if unit.lower() not in UNIT_FACTORS:
            _fail(f"timestamp.unit: unknown unit {unit!r}", path)
        kw["time_scale"] = float(t.num(ts, "scale", "timestamp.", 1.0, lo=0, lo_open=True)) \
            * UNIT_FACTORS[unit.lower()]
        bits = int(t.num(ts, "bits", "timestamp.", 32, lo=1, hi=64, integer=True))
        kw["time_bits"] = bits
        kw["time_modulus"] = t.num(ts, "modulus", "timestamp.", float(2 ** bits), lo=0,
                                   lo_open=True)
    noise = t.table(raw, "noise")
    for k in noise:
        t.num(noise, k, "noise.", lo=0)
    if len(kw.get("layouts", ())) > 1:  # temp is a channel when every datagram has it
        with_temp = all(any(f.name == "temp" for f in lay.fields) for lay in kw["layouts"])
        all_fields = tuple(f for f in all_fields if f.name != "temp" or with_temp)
    kw["channels"] = _channels(all_fields, path)
    binary = fmt == "binary"
    kw["configure"] = _steps(t, raw, "configure", binary)
    kw["start_steps"] = _steps(t, raw, "start", binary)
    kw["stop_steps"] = _steps(t, raw, "stop", binary)
    kw["identify"] = _steps(t, raw, "identify", binary)
    if fmt == "can" and (kw["configure"] or kw["start_steps"] or kw["identify"]):
        _fail("configuration steps are for serial profiles", path)
    kw["base_rate_hz"] = t.num(raw, "base_rate_hz", "", None, lo=0, hi=MAX_RATE_HZ, lo_open=True)
    codes = t.table(raw, "rate_codes")
    kw["rate_codes"] = {float(k): int(t.num(codes, k, "rate_codes.", lo=0, hi=2**32 - 1,
                                            integer=True)) for k in codes
                        if _is_number(k, t)}
    kw["document"] = t.text(raw, "document", "", "")
    return ImuProfile(name=t.text(raw, "name", "", Path(path).stem) or Path(path).stem,
                      path=path, format=fmt, rate_hz=float(rate), transport=transport,
                      raw_text=text, **kw)


def _is_number(key: str, t: Typed) -> bool:
    try:
        v = float(key)
    except ValueError:
        t.fail(f"rate_codes: the keys are rates in Hz, got {key!r}")
    if not np.isfinite(v) or v <= 0:
        t.fail(f"rate_codes: the keys are positive rates in Hz, got {key!r}")
    return True


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
    t = Typed(path)  # typed values: a number is a number (issue 37)
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
                        settled_states=settled,
                        terminator=t.text(raw, "terminator", "", "\r\n", allow_empty=False),
                        timeout_s=float(t.num(raw, "timeout_s", "", 60.0, lo=0, hi=86400,
                                              lo_open=True)),
                        speed_dps=float(t.num(raw, "speed_dps", "", 90.0, lo=0, hi=1e5,
                                              lo_open=True)), axes=axes)


def load_table_profile(path) -> TableProfile:
    if str(path) == "manual":
        return TableProfile(name="manual", path="manual", kind="manual")
    p = resolve_profile(str(path), "turntable")
    return parse_table_profile(_read_named(str(path), p, "turntable"), p)


def _can_messages(t, raw: dict, path: str, byte_order: str):
    """(messages, dbc database or None) of a CAN profile."""
    from calib_cli.acquire.candbc import CAN_TYPES, load_dbc  # cantools only for a DBC profile

    dbc = None
    if "dbc" in raw:
        name = t.text(raw, "dbc", "", allow_empty=False)
        p = Path(name)
        dbc_path = str(p if p.is_absolute() else Path(path).parent / p)
        dbc = load_dbc(dbc_path)
    bo = "<" if byte_order == "little" else ">"
    msgs = []
    for i, m in enumerate(t.tables(raw, "message", limit=64)):
        where = f"message {i + 1}"
        t.keys(m, IMU_KEYS["message"], f"{where}: ")
        for j, f in enumerate(t.tables(m, "field", limit=64)):
            t.keys(f, FIELD_KEYS, f"{where} field {j + 1}: ")
        if isinstance(m.get("checksum"), dict):
            t.keys(m["checksum"], CHECKSUM_KEYS, f"{where} checksum: ")
        if dbc is not None:
            msgs.append(_dbc_message(t, m, where, dbc, _field))
            continue
        if "id" not in m:
            t.fail(f"{where}: needs an arbitration id")
        cid = int(t.num(m, "id", f"{where}: ", lo=0, hi=0x1FFFFFFF, integer=True))
        flds = tuple(_field(t, f, f"{where} field {j + 1}", True)
                     for j, f in enumerate(m.get("field", [])))
        if any(f.type not in CAN_TYPES for f in flds):
            t.fail(f"{where}: CAN fields are 8, 16, 32 or 64 bits")
        pos, placed = 0, []
        for f in flds:
            off = pos if f.offset is None else f.offset
            placed.append(dataclasses.replace(f, offset=off))
            pos = off + struct.calcsize(bo + CAN_TYPES[f.type])
        cs = _checksum(t, m.get("checksum"), f"{where}.checksum") if "checksum" in m \
            else Checksum()
        length = int(t.num(m, "length", f"{where}: ", pos + cs.nbytes, lo=0, hi=8,
                           integer=True))
        if pos + cs.nbytes > length:
            t.fail(f"{where}: fields and checksum need {pos + cs.nbytes} bytes; a classic CAN "
                   "frame holds 8")
        msgs.append(CanMessage(cid, t.flag(m, "extended", f"{where}: "), tuple(placed), cs,
                               length))
    if not msgs:
        t.fail("a CAN profile needs [[message]] entries")
    return tuple(msgs), dbc


def _dbc_message(t, m: dict, where: str, dbc, make_field):
    name = t.text(m, "name", f"{where}: ", allow_empty=False)
    try:
        msg = dbc.get_message_by_name(name)
    except KeyError:
        t.fail(f"{where}: the DBC file has no message {name!r}; it has "
               f"{', '.join(x.name for x in dbc.messages)}")
    flds = []
    for j, f in enumerate(t.tables(m, "field", limit=64)):
        sig = t.text(f, "signal", f"{where} field {j + 1}: ", allow_empty=False)
        if sig not in msg.signal_tree:
            t.fail(f"{where} field {j + 1}: message {name!r} has no signal {sig!r}")
        fd = make_field(t, {k: v for k, v in f.items() if k != "signal"},
                        f"{where} field {j + 1}", False)
        flds.append(dataclasses.replace(fd, literal=sig))  # literal: the DBC signal name
    return CanMessage(msg.frame_id, msg.is_extended_frame, tuple(flds), Checksum(),
                      msg.length, name)
