"""The configuration exchange with a unit, from its profile (docs/acquisition.md):
``[[configure]]`` steps (output rate, data, units), ``[[start]]`` (go to
measurement), ``[[stop]]`` (a clean stop on exit) and ``[[identify]]`` (a
harmless identification request for ``--imu auto``).

A step's ``send`` and ``expect`` are templates: hex bytes (binary) or text with
placeholders {rate} (the output rate, Hz), {div} (base_rate_hz / rate) and
{code} (rate_codes[rate]); in hex, {rate:u16be} and the like give the width and
byte order. ``checksum = "frame"`` appends the profile's frame checksum,
``"nmea"`` the ``*XX`` XOR and CR LF after a text. The same templates drive
the emulator's answers (``Responder``), so a profile is tried without hardware,
configuration exchange included.
"""

from __future__ import annotations

import re
import struct
import time

from calib_cli.errors import InputError

_PH = re.compile(r"\{(rate|div|code)(?::(u8|u16be|u16le|u32be|u32le|f32be|f32le))?\}")
_ENC = {"u8": ">B", "u16be": ">H", "u16le": "<H", "u32be": ">I", "u32le": "<I", "f32be": ">f",
        "f32le": "<f"}


def check_template(tpl: str, text: bool) -> str | None:
    """None, or what is wrong with a step template."""
    if text:
        for m in re.finditer(r"\{([^}]*)\}", tpl):
            if m.group(1) not in ("rate", "div", "code"):
                return f"unknown placeholder {{{m.group(1)}}} (known: {{rate}} {{div}} {{code}})"
        return None
    rest = _PH.sub(" ", tpl)
    if "{" in rest or "}" in rest:
        return (f"bad placeholder in {tpl!r}: use {{rate:u16be}}, {{div:u8}}, {{code:u8}} "
                "(u8 u16be u16le u32be u32le f32be f32le)")
    try:
        bytes.fromhex(rest)
    except ValueError:
        return f"not hex bytes: {tpl!r}"
    return None


def rate_values(prof, rate: float) -> dict:
    """The placeholder values at ``rate`` Hz."""
    out = {"rate": rate}
    if prof.base_rate_hz:
        div = prof.base_rate_hz / rate
        if abs(div - round(div)) > 1e-6 or div < 1:
            raise InputError(f"{rate:g} Hz is not the base rate {prof.base_rate_hz:g} Hz divided "
                             "by a whole number: choose --rate accordingly", prof.path)
        out["div"] = int(round(div))
    if prof.rate_codes:
        code = prof.rate_codes.get(float(rate))
        if code is None:
            raise InputError(f"the unit cannot output {rate:g} Hz; its rates: "
                             f"{', '.join(f'{r:g}' for r in sorted(prof.rate_codes))} Hz",
                             prof.path)
        out["code"] = code
    return out


def _value(name: str, vals: dict, where: str):
    if name not in vals:
        raise InputError(f"{where}: {{{name}}} needs "
                         f"{'base_rate_hz' if name == 'div' else 'rate_codes'} in the profile")
    return vals[name]


def _nmea(body: bytes) -> bytes:
    x = 0
    for b in body[1:] if body[:1] == b"$" else body:
        x ^= b
    return body + f"*{x:02X}\r\n".encode()


def _frame_checksum(prof, data: bytes) -> bytes:
    cs = prof.checksum
    a = cs.start(len(prof.sync), len(prof.sync))
    return data + cs.compute(data[a:]).to_bytes(cs.nbytes, cs.byte_order)


def render(prof, tpl: str, text: bool, checksum: str, vals: dict) -> bytes:
    """The bytes of a template at the placeholder values ``vals``."""
    if text:
        body = re.sub(r"\{(rate|div|code)\}",
                      lambda m: f"{_value(m.group(1), vals, tpl):g}", tpl)
        data = body.encode("latin-1").decode("unicode_escape").encode("latin-1")
    else:
        out = b""
        pos = 0
        for m in _PH.finditer(tpl):
            out += bytes.fromhex(tpl[pos:m.start()])
            v = _value(m.group(1), vals, tpl)
            enc = _ENC[m.group(2) or "u8"]
            out += struct.pack(enc, v if "f" in enc else int(v))
            pos = m.end()
        data = out + bytes.fromhex(tpl[pos:])
    if checksum == "nmea":
        return _nmea(data)
    if checksum == "frame":
        return _frame_checksum(prof, data)
    return data


def pattern(prof, tpl: str, text: bool) -> re.Pattern:
    """A bytes regex matching the template at any placeholder value (named
    groups ``rate``, ``div``, ``code``), checksum excluded."""
    if text:
        parts, pos = [], 0
        seen = set()
        for m in re.finditer(r"\{(rate|div|code)\}", tpl):
            parts.append(re.escape(tpl[pos:m.start()].encode("latin-1").decode(
                "unicode_escape").encode("latin-1")))
            name = m.group(1).encode()
            parts.append(rb"(?P=" + name + rb")" if name in seen else
                         rb"(?P<" + name + rb">[0-9.+-]+)")
            seen.add(name)
            pos = m.end()
        parts.append(re.escape(tpl[pos:].encode("latin-1").decode("unicode_escape")
                               .encode("latin-1")))
        return re.compile(b"".join(parts), re.S)
    parts, pos, seen = [], 0, set()
    for m in _PH.finditer(tpl):
        parts.append(re.escape(bytes.fromhex(tpl[pos:m.start()])))
        size = struct.calcsize(_ENC[m.group(2) or "u8"])
        name = m.group(1).encode()
        if name in seen:  # the same value again (a rate per output): must repeat it
            parts.append(rb"(?P=" + name + rb")")
        else:
            seen.add(name)
            parts.append(rb"(?P<" + name + rb">.{" + str(size).encode() + rb"})")
        pos = m.end()
    parts.append(re.escape(bytes.fromhex(tpl[pos:])))
    return re.compile(b"".join(parts), re.S)


def decode_value(tpl: str, name: str, raw: bytes, text: bool) -> float:
    if text:
        return float(raw)
    m = next(m for m in _PH.finditer(tpl) if m.group(1) == name)
    return struct.unpack(_ENC[m.group(2) or "u8"], raw)[0]


# ---------------------------------------------------------------------------
# the host side: run steps over a serial transport


class ExchangeError(InputError):
    pass


def run_steps(transport, prof, steps, rate: float, what: str, log: list) -> dict:
    """Send each step and wait for its expected reply; the replies of steps
    with ``readback`` are returned {name: reply text or hex}. ``log`` gets one
    line a step. Raises ExchangeError naming the port when a reply does not
    come within timeout_s after every retry."""
    vals = rate_values(prof, rate)
    out = {}
    for i, st in enumerate(steps):
        cmd = render(prof, st.send, st.text, st.checksum, vals)
        # expect is the whole checksummed reply, or (with a reply for the emulator) a prefix
        want = render(prof, st.expect, st.text, "none" if st.reply else st.checksum, vals) \
            if st.expect else None
        got = None
        for _attempt in range(st.retries + 1):
            transport.write(cmd)
            if want is None:
                got = b""
                break
            got = await_reply(transport, want, st.timeout_s)
            if got is not None:
                break
        label = st.description or f"{what} step {i + 1}"
        if got is None:
            raise ExchangeError(
                f"{label}: no acknowledgement {_show(want, st.text)} to {_show(cmd, st.text)} "
                f"within {st.timeout_s:g} s ({st.retries + 1} tries): check the port, the baud "
                f"rate and that the unit is a {prof.name}", getattr(transport, "port", None))
        log.append(f"{label}: sent {_show(cmd, st.text)}"
                   + (f", acknowledged {_show(got, st.text)}" if want else ""))
        if st.readback:
            out[st.readback] = _show(got, st.text)
        if st.delay_s:
            time.sleep(st.delay_s)
    return out


def _show(data: bytes | None, text: bool) -> str:
    if data is None:
        return "(none)"
    if text:
        return data.decode("latin-1").strip()
    return data.hex(" ").upper()


def await_reply(transport, want: bytes, timeout_s: float) -> bytes | None:
    """Read until ``want`` appears (the unit may be streaming meanwhile)."""
    buf = bytearray()
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        try:
            buf += transport.read()
        except Exception:  # noqa: BLE001 - a port that fails here fails again later
            return None
        if want in buf:
            return want
        if len(buf) > 1 << 20:
            del buf[:-len(want)]
    return None


# ---------------------------------------------------------------------------
# the device side: the emulator's answers


class Responder:
    """Answers a profile's configuration steps like the unit would: each step's
    ``send`` pattern is recognised in what the host writes, the rate it carries
    is taken, and the rendered ``reply`` (default ``expect``) is answered.
    ``streaming`` follows the start and stop steps; ``rate_requests`` keeps the
    rates asked for."""

    def __init__(self, prof, rate: float):
        self.prof, self.rate = prof, rate
        self.buf = b""
        self.streaming = True
        self.rate_requests: list[float] = []
        self.log: list[str] = []
        self.rules = []
        # a command that is both a configuration step and the stop (GoToConfig) stops
        for kind, steps in (("stop", prof.stop_steps), ("start", prof.start_steps),
                            ("configure", prof.configure), ("identify", prof.identify)):
            for st in steps:
                self.rules.append((kind, st, pattern(prof, st.send, st.text)))

    def feed(self, data: bytes) -> bytes:
        self.buf = (self.buf + data)[-4096:]
        out = b""
        while True:
            best = None
            for kind, st, pat in self.rules:
                m = pat.search(self.buf)
                if m and (best is None or m.start() < best[2].start()):
                    best = (kind, st, m)
            if best is None:
                return out
            kind, st, m = best
            self.buf = self.buf[m.end():]
            vals = {"rate": self.rate}
            try:
                vals.update(rate_values(self.prof, self.rate))
            except InputError:
                pass
            for name in ("rate", "div", "code"):
                if name in m.groupdict() and m.group(name) is not None:
                    v = decode_value(st.send, name, m.group(name), st.text)
                    vals[name] = v
                    self.rate_requests.append(self._rate_of(name, v))
            self.log.append(f"{kind}: {_show(m.group(0), st.text)}")
            if kind == "start":
                self.streaming = True
            elif kind == "stop":
                self.streaming = False
            reply = st.reply or st.expect
            if reply is not None:
                out += render(self.prof, reply, st.text, st.checksum, vals)

    def _rate_of(self, name: str, v: float) -> float:
        if name == "div" and self.prof.base_rate_hz:
            return self.prof.base_rate_hz / v
        if name == "code":
            inv = {c: r for r, c in self.prof.rate_codes.items()}
            return inv.get(int(v), float("nan"))
        return float(v)


def write_device_info(path: str, prof, info: dict) -> None:
    """The unit's configuration exchange and read-back into raw.h5 (group
    ``/acquisition``: attributes ``imu_profile``, ``profile_document``,
    ``rate_hz``, ``exchange`` and ``readback`` as JSON)."""
    import json

    from calib_cli.io.h5file import h5_writer, set_attrs

    # through the checked writer: a full disk is exit 2 naming the file (issue 37)
    with h5_writer(path, "r+") as h5:
        g = h5.require_group("acquisition")
        set_attrs(g, {"imu_profile": prof.name, "profile_document": prof.document,
                      "rate_hz": float(info.get("rate_hz", prof.rate_hz)),
                      "exchange": json.dumps(info.get("exchange", [])),
                      "readback": json.dumps(info.get("readback", {}))})
