"""Which known protocol a serial port speaks (``calib record --imu auto``,
``calib profiles --probe PORT``).

First passively: at each baud rate the serial profiles use, listen for a while
and run every profile's decoder over what arrived; a profile whose frames pass
their checksums (at least ``MIN_FRAMES``) is a match. Then, when nothing
streams, actively: send each profile's ``[[identify]]`` request (a harmless
identification query: Xsens ReqDID, MIP Ping, VectorNav model register, Epson
product id) and wait for its expected answer."""

from __future__ import annotations

import time
from dataclasses import dataclass

from calib_cli.errors import InputError

MIN_FRAMES = 3


@dataclass
class Found:
    name: str
    how: str  # passive | identify
    detail: str


def candidate_profiles() -> list:
    """The serial IMU profiles along the profile search path (user profiles
    first, shadowed ones left out); ones that do not load are skipped."""
    from calib_cli.acquire.profile import parse_imu_profile
    from calib_cli.io.profiles import all_profiles

    out = []
    for p in all_profiles(("imu",)):
        if p["shadowed"]:
            continue
        try:
            with open(p["path"], encoding="utf-8") as fh:
                prof = parse_imu_profile(fh.read(), p["path"])
        except (InputError, OSError, UnicodeDecodeError):
            continue
        if prof.format != "can" and (prof.transport or {}).get("kind", "serial") == "serial":
            out.append(prof)
    return out


def _baud(prof) -> int:
    return int((prof.transport or {}).get("baudrate", 115200))


def passive(data: bytes, profiles) -> list[Found]:
    """The profiles whose decoders accept at least MIN_FRAMES frames of ``data``
    (most frames first)."""
    from calib_cli.acquire.codec import make_decoder

    hits = []
    for prof in profiles:
        dec = make_decoder(prof)
        items = dec.feed(data)
        good = sum(1 for it in items if it is not None)
        bad = len(items) - good
        if good >= MIN_FRAMES and good >= bad:
            hits.append((good, Found(prof.name, "passive",
                                     f"{good} frames with good checksums, {bad} rejected")))
    return [f for _, f in sorted(hits, key=lambda h: -h[0])]


def probe_port(port: str, profiles=None, listen_s: float = 0.6, active: bool = True,
               open_transport=None) -> list[Found]:
    """What the unit on ``port`` speaks: passive matches at each baud rate, else
    the profiles whose identification request was answered. Empty: no known
    protocol. ``open_transport(port, settings)``: for tests."""
    from calib_cli.acquire.device import await_reply, rate_values, render
    from calib_cli.acquire.transport import SerialTransport

    profiles = candidate_profiles() if profiles is None else profiles
    opener = open_transport or (lambda p, s: SerialTransport(p, s))
    bauds = sorted({_baud(p) for p in profiles}, reverse=True)
    for baud in bauds:
        tr = opener(port, {"baudrate": baud})
        tr.open()
        try:
            data = bytearray()
            t_end = time.monotonic() + listen_s
            while time.monotonic() < t_end:
                data += tr.read()
        finally:
            tr.close()
        found = passive(bytes(data), [p for p in profiles if _baud(p) == baud] or profiles)
        if found:
            for f in found:
                f.detail += f" at {baud} baud"
            return found
    if not active:
        return []
    out = []
    for prof in profiles:
        if not prof.identify:
            continue
        tr = opener(port, {"baudrate": _baud(prof)})
        tr.open()
        try:
            try:
                vals = rate_values(prof, prof.rate_hz)
            except InputError:
                vals = {"rate": prof.rate_hz}
            ok = True
            for st in prof.identify:
                tr.write(render(prof, st.send, st.text, st.checksum, vals))
                want = render(prof, st.expect, st.text, "none" if st.reply else st.checksum,
                              vals) if st.expect else b""
                if want and await_reply(tr, want, min(st.timeout_s, 0.5)) is None:
                    ok = False
                    break
        finally:
            tr.close()
        if ok:
            out.append(Found(prof.name, "identify",
                             f"answered {prof.identify[-1].description or 'identify'} at "
                             f"{_baud(prof)} baud"))
    return out


def no_protocol_message(port: str, profiles) -> str:
    bauds = ", ".join(str(b) for b in sorted({_baud(p) for p in profiles}))
    asked = ", ".join(p.name for p in profiles if p.identify) or "none"
    return (f"no known protocol on {port}: nothing decoded at {bauds} baud, and no answer to "
            f"the identification requests of {asked}; check the wiring and power, or give "
            "--imu PROFILE (a profile for this unit: docs/acquisition.md)")
