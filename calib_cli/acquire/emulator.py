"""A virtual IMU (and turntable) speaking a profile's protocol over a pty or CAN.

The unit's motion comes from ``model.kinematics`` and its outputs from the
truth model (``ImuModel.predict`` plus the noise effects' seeded realisation,
exactly as ``sim/`` does: ``Emulator.samples``), so a
recording of the emulator can be fitted and compared with the truth. The
virtual table obeys the commands of a table profile and moves the unit.

The encoders here are written apart from the decoders in ``codec.py`` (numpy
record arrays and int.to_bytes here, struct there), and both are checked
against hand-written golden vectors, so a bug cannot hide in both.

Faults (``Faults``): corrupted frames (one byte changed, in the payload and
checksum or anywhere in the frame), dropped frames, garbage bursts between
frames and a disconnect; ``Emulator.injected`` counts what was done.
"""

from __future__ import annotations

import os
import re
import shutil
import string
import tempfile
import threading
import time
import tty
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from calib_cli.acquire.profile import TYPE_SIZE, ImuProfile, TableProfile
from calib_cli.errors import InputError
from calib_cli.model import kinematics as kn
from calib_cli.model.earth import Site
from calib_cli.model.effects import Layout
from calib_cli.model.frames import attitude_to_rotation, rotation_to_attitude
from calib_cli.model.truth import Truth, default_truth

D2R = np.pi / 180.0
NP_TYPES = {"u8": "u1", "i8": "i1", "u16": "u2", "i16": "i2", "u24": "i4", "i24": "i4",
            "u32": "u4", "i32": "i4",
            "u64": "u8", "i64": "i8", "f32": "f4", "f64": "f8"}
FIFO_LIMIT = 1 << 20  # bytes the virtual device buffers before it drops frames
STALL_S = 1.0  # no byte taken for this long: nobody listens, the queue is discarded


@dataclass
class Faults:
    """Fault injection, per frame probabilities. corrupt_where: "payload"
    (payload or checksum bytes: each one is a checksum error) or "anywhere"
    (any byte of the frame, sync, length and delimiters too)."""

    corrupt: float = 0.0
    corrupt_where: str = "payload"
    drop: float = 0.0
    garbage: float = 0.0
    garbage_max: int = 40
    disconnect_at: float | None = None  # s after start
    disconnect_for: float = 1.0  # s
    seed: int = 1


# ---------------------------------------------------------------------------
# encoders (independent of codec.py)


class BinaryEncoder:
    """Frames of one layout (``layout``: its index; datagrams of a STIM300 profile),
    built as a byte matrix column by column with numpy (record fields, 24-bit
    integers, tagged records with their constant headers)."""

    def __init__(self, prof: ImuProfile, layout: int = 0):
        self.prof = prof
        self.lay = lay = prof.layouts[layout]
        self.cs = prof.checksum
        self.bo = "<" if prof.byte_order == "little" else ">"
        if lay.tagged is None:
            self.parts = [(f, None) for f in lay.fields]
        else:
            tg = lay.tagged
            self.parts = []
            sizes = lay.tag_sizes()
            for tag, size in sizes.items():
                n = size + (tg.header_size if tg.length_includes_header else 0)
                idb = tag.to_bytes(TYPE_SIZE[tg.id_type], tg.byte_order)
                lnb = n.to_bytes(TYPE_SIZE[tg.length_type], tg.byte_order)
                head = idb + lnb if tg.order == "id-length" else lnb + idb
                self.parts.append((None, head))
                flds = sorted((f for f in lay.fields if f.tag == tag), key=lambda f: f.offset)
                pos = 0
                for f in flds:
                    if f.offset > pos:
                        self.parts.append((None, bytes(f.offset - pos)))
                    self.parts.append((f, None))
                    pos = f.offset + TYPE_SIZE[f.type]
                if size > pos:
                    self.parts.append((None, bytes(size - pos)))
        psize = lay.payload_size
        if lay.length_type:
            n = psize + (self.cs.nbytes if lay.length_covers != "payload" else 0)
            self.len_bytes = n.to_bytes(TYPE_SIZE[lay.length_type], lay.length_order)
        else:
            self.len_bytes = b""
        self.payload_offset = len(lay.sync) + len(self.len_bytes)
        self.cs_start = self.cs.start(len(lay.sync), self.payload_offset)

    def _column(self, f, values, k: int) -> np.ndarray:
        x = _to_type(values.get(f.name, np.zeros(k)), f.type)
        size = TYPE_SIZE[f.type]
        if size == 3:  # 24-bit two's complement: the low three bytes of an int32
            b = x.astype(self.bo + "i4").view(np.uint8).reshape(k, 4)
            return b[:, :3] if self.bo == "<" else b[:, 1:]
        return np.ascontiguousarray(x.astype(self.bo + NP_TYPES[f.type])).view(
            np.uint8).reshape(k, size)

    def encode(self, values: dict) -> list[bytes]:
        """values: field name -> raw numbers (k,). Returns k whole frames."""
        k = len(next(iter(values.values())))
        cols = [np.frombuffer(self.lay.sync + self.len_bytes, np.uint8)[None, :].repeat(k, 0)]
        for f, const in self.parts:
            cols.append(np.frombuffer(const, np.uint8)[None, :].repeat(k, 0) if f is None
                        else self._column(f, values, k))
        blob = np.concatenate(cols, axis=1) if k else np.empty((0, 0), np.uint8)
        out = []
        cs, a, end = self.cs, self.cs_start, self.lay.end
        for i in range(k):
            frame = blob[i].tobytes()
            if cs.nbytes:
                frame += cs.compute(frame[a:]).to_bytes(cs.nbytes, cs.byte_order)
            out.append(frame + end)
        return out

    def payload_span(self, frame: bytes) -> tuple[int, int]:
        """[a, b): the payload and checksum bytes of a frame."""
        return self.payload_offset, len(frame) - len(self.lay.end)


class AsciiEncoder:
    def __init__(self, prof: ImuProfile):
        self.prof = prof
        self.ints = {prof.seq_field, prof.time_field}

    def encode(self, values: dict) -> list[bytes]:
        p = self.prof
        k = len(next(iter(values.values())))
        cols = []
        for f in p.fields:
            if f.literal is not None:
                cols.append([f.literal] * k)
            elif f.name in self.ints:
                cols.append([str(int(v)) for v in values[f.name]])
            else:
                cols.append([f"{v:.6f}" for v in values.get(f.name, np.zeros(k))])
        out = []
        for i in range(k):
            body = p.delimiter.join(c[i] for c in cols)
            s = p.start + body
            if p.checksum.kind != "none":
                x = p.checksum.compute(body.encode())
                s += f"{p.separator}{x:0{p.hex_digits}X}"
            out.append((s + p.terminator).encode())
        return out

    def payload_span(self, frame: bytes) -> tuple[int, int]:
        """The body and checksum digits (not the start, separator, terminator)."""
        return len(self.prof.start), len(frame) - len(self.prof.terminator)


class CanEncoder:
    def __init__(self, prof: ImuProfile):
        self.prof = prof

    def _dbc(self, m, values: dict, i: int) -> bytes:
        return _dbc_encode(self.prof, m, values, i)

    def encode(self, values: dict) -> list[list[tuple[int, bool, bytes]]]:
        k = len(next(iter(values.values())))
        out = []
        for i in range(k):
            msgs = []
            for m in self.prof.messages:
                if m.dbc_name is not None:
                    msgs.append((m.can_id, m.extended, self._dbc(m, values, i)))
                    continue
                data = bytearray(m.length)
                for f in m.fields:
                    v = _to_type(np.asarray([values[f.name][i]]), f.type)[0]
                    if f.type.startswith("f"):
                        b = np.asarray(v, dtype=("<" if self.prof.byte_order == "little" else ">")
                                       + NP_TYPES[f.type]).tobytes()
                    else:
                        b = int(v).to_bytes(int(NP_TYPES[f.type][1:]), self.prof.byte_order,
                                            signed=f.type.startswith("i"))
                    data[f.offset:f.offset + len(b)] = b
                if m.checksum.nbytes:
                    kk = m.length - m.checksum.nbytes
                    data[kk:] = m.checksum.compute(bytes(data[:kk])).to_bytes(
                        m.checksum.nbytes, m.checksum.byte_order)
                msgs.append((m.can_id, m.extended, bytes(data)))
            out.append(msgs)
        return out


def _dbc_encode(prof, m, values: dict, i: int) -> bytes:
    """A DBC message by cantools: the profile's fields in the DBC's units, every
    other signal at zero (clipped to its range)."""
    msg = prof.dbc.get_message_by_frame_id(m.can_id)
    sig = {}
    for s in msg.signals:
        lo = s.minimum if s.minimum is not None else 0.0
        hi = s.maximum if s.maximum is not None else 0.0
        sig[s.name] = min(max(0.0, lo), hi) if hi >= lo else 0.0
    for f in m.fields:
        s = msg.get_signal_by_name(f.literal)
        v = float(values[f.name][i])
        step = s.scale or 1.0  # whole raw steps, within the signal's range
        v = s.offset + round((v - s.offset) / step) * step
        lo = s.minimum if s.minimum is not None else -np.inf
        hi = s.maximum if s.maximum is not None else np.inf
        sig[f.literal] = min(max(v, lo), hi)
    return msg.encode(sig, scaling=True, strict=False)


def _to_type(x, typ: str) -> np.ndarray:
    x = np.asarray(x, dtype=float)
    if typ.startswith("f"):
        return x
    if typ in ("u24", "i24"):
        lo, hi = (0, 2**24 - 1) if typ == "u24" else (-2**23, 2**23 - 1)
    else:
        info = np.iinfo(NP_TYPES[typ])
        lo, hi = info.min, info.max
    return np.clip(np.rint(x), lo, hi).astype(np.int64)


def make_encoder(prof: ImuProfile, layout: int = 0):
    if prof.format == "binary":
        return BinaryEncoder(prof, layout)
    return {"ascii": AsciiEncoder, "can": CanEncoder}[prof.format](prof)


# ---------------------------------------------------------------------------
# the virtual unit on its virtual table


class VirtualUnit:
    """Attitude and motion of the unit: static, slewing (minimum-jerk, from
    kinematics.slew_kinematics) or turning at a constant rate about ENU up."""

    def __init__(self, site: Site, fs: float, attitude=(0.0, 0.0, 0.0), speed_dps=90.0):
        self.site, self.fs = site, fs
        self.rot = attitude_to_rotation(np.asarray(attitude, float))
        self.speed = speed_dps * D2R
        self.mode = "static"
        self.slew = None  # (k0, Kinematics of the whole slew, target rotation)
        self.rate = 0.0
        self.rate_k0 = 0
        self.rate_rot0 = self.rot

    def state(self) -> str:
        return {"static": "IDLE", "slew": "MOVING", "rate": "RATE"}[self.mode]

    def move_to(self, target: Rotation, k_now: int) -> None:
        self._freeze(k_now)
        ang = (self.rot.inv() * target).magnitude()
        dur = max(ang / self.speed, 0.05)
        n = max(int(round(dur * self.fs)), 2)
        t = (k_now + np.arange(n)) / self.fs
        self.slew = (k_now, kn.slew_kinematics(t, self.rot, target, self.site), target)
        self.mode = "slew"

    def set_rate(self, rate: float, k_now: int) -> None:
        self._freeze(k_now)
        if rate == 0.0:
            self.mode = "static"
            return
        self.mode, self.rate, self.rate_k0, self.rate_rot0 = "rate", rate, k_now, self.rot

    def _freeze(self, k_now: int) -> None:
        """Stop where the unit is now."""
        self.rot = self.rotation_at(k_now)
        self.mode = "static"

    def rotation_at(self, k: int) -> Rotation:
        if self.mode == "slew":
            k0, kin, target = self.slew
            if k - k0 >= len(kin):
                return target
            # re-derive the attitude along the slew from its rotation vector
            n = len(kin)
            u = (k - k0) / (n - 1)
            s = 10 * u**3 - 15 * u**4 + 6 * u**5
            phi = (self.rot.inv() * target).as_rotvec()
            return self.rot * Rotation.from_rotvec(s * phi)
        if self.mode == "rate":
            th = self.rate * (k - self.rate_k0) / self.fs
            return Rotation.from_rotvec([0, 0, th]) * self.rate_rot0
        return self.rot

    def kinematics(self, k0: int, n: int) -> kn.Kinematics:
        t = (k0 + np.arange(n)) / self.fs
        if self.mode == "slew":
            ks, kin, target = self.slew
            a = k0 - ks
            if a + n <= len(kin):
                return kin.take(slice(a, a + n))
            m = max(len(kin) - a, 0)
            self.rot, self.mode = target, "static"
            rest = self.kinematics(k0 + m, n - m)
            return rest if m == 0 else kn.Kinematics.concatenate([kin.take(slice(a, a + m)),
                                                                  rest])
        if self.mode == "rate":
            th = self.rate * (k0 + np.arange(n) - self.rate_k0) / self.fs
            rot0 = Rotation.from_rotvec([0, 0, th[0]]) * self.rate_rot0
            return kn.table_kinematics(t, [0, 0, 1], th, np.full(n, self.rate), np.zeros(n),
                                       rot0, self.site)
        return kn.from_attitude(t, Rotation.from_quat(np.tile(self.rot.as_quat(), (n, 1))),
                                self.site)


def _template_regex(tpl: str) -> re.Pattern:
    parts = []
    for lit, name, _spec, _conv in string.Formatter().parse(tpl):
        parts.append(re.escape(lit))
        if name:
            parts.append(rf"(?P<{name}>[-+0-9.eE]+)")
    return re.compile("^" + "".join(parts) + "$")


class VirtualTable:
    """Parses commands by the profile's templates and answers with its replies."""

    def __init__(self, prof: TableProfile, unit: VirtualUnit):
        self.prof, self.unit = prof, unit
        self.patterns = {k: _template_regex(v) for k, v in prof.commands.items()}
        self.target = rotation_to_attitude(unit.rot) / D2R
        self.inbuf = b""
        self.log: list[str] = []

    def _reply(self, name: str, **kw) -> bytes:
        tpl = self.prof.replies.get(name, {"ack": "OK", "error": "ERR"}.get(name, ""))
        return (tpl.format(**kw) + self.prof.terminator).encode()

    def handle(self, line: str, k_now: int) -> bytes:
        self.log.append(line)
        for name, pat in self.patterns.items():
            m = pat.match(line)
            if not m:
                continue
            vals = {k: float(v) for k, v in m.groupdict().items()}
            if name == "move":
                for i, a in enumerate(("roll", "pitch", "yaw")):
                    if f"{a}_deg" in vals:
                        self.target[i] = vals[f"{a}_deg"]
                self.unit.move_to(attitude_to_rotation(self.target * D2R), k_now)
                return self._reply("ack")
            if name == "rate":
                self.unit.set_rate(vals["rate_dps"] * D2R, k_now)
                return self._reply("ack")
            if name == "stop":
                self.unit.set_rate(0.0, k_now)
                return self._reply("ack")
            if name == "query_angle":
                att = rotation_to_attitude(self.unit.rotation_at(k_now)) / D2R
                return self._reply("angle", roll_deg=att[0], pitch_deg=att[1], yaw_deg=att[2])
            if name == "query_status":
                return self._reply("status", state=self.unit.state())
        return self._reply("error")

    def feed(self, data: bytes, k_now: int) -> bytes:
        self.inbuf += data
        term = self.prof.terminator.encode()
        out = b""
        # accept \r, \n or the terminator as the end of a command
        while True:
            m = re.search(rb"\r\n|\r|\n", self.inbuf)
            if not m:
                break
            line = self.inbuf[:m.start()].decode("ascii", "replace").strip()
            self.inbuf = self.inbuf[m.end():]
            if line:
                out += self.handle(line, k_now)
        del term
        return out


# ---------------------------------------------------------------------------
# the virtual climatic chamber (issue 21)


class ChamberPhysics:
    """The chamber air moves towards the setpoint at its ramp rate (the rate
    commanded, at most the profile's ``max_ramp_dpm``; 5 degC/min when
    neither is given), and the unit follows the air with a first-order
    response of time constant ``tau`` (s): exact per sample for the air
    constant over a sample period. The unit starts soaked at ``start``."""

    def __init__(self, start: float, tau: float, max_ramp_dpm: float | None, fs: float):
        self.air = self.unit = self.setpoint = float(start)
        self.tau, self.fs = max(float(tau), 1e-9), fs
        self.max_rate = max_ramp_dpm
        self.rate = max_ramp_dpm or 5.0  # degC/min

    def set_rate(self, dpm: float) -> None:
        self.rate = min(abs(float(dpm)), self.max_rate) if self.max_rate else abs(float(dpm))

    def advance(self, n: int) -> np.ndarray:
        """The unit's temperature at the next n samples."""
        from scipy.signal import lfilter

        step = self.rate / 60.0 / self.fs
        gap = self.setpoint - self.air
        air = self.air + np.sign(gap) * np.minimum(step * np.arange(1, n + 1), abs(gap))
        a = np.exp(-1.0 / (self.fs * self.tau))
        unit, _ = lfilter([1.0 - a], [1.0, -a], air, zi=[a * self.unit])
        self.air, self.unit = float(air[-1]), float(unit[-1])
        return unit


class VirtualChamber:
    """Answers a chamber profile's protocol: SCPI-style lines (the profile's
    command templates and reply templates) or Modbus RTU frames (a slave
    with the profile's registers; a frame with a bad CRC gets no reply)."""

    def __init__(self, prof, phys: ChamberPhysics):
        self.prof, self.phys = prof, phys
        self.inbuf = b""
        self.log: list = []
        if prof.kind == "scpi":
            self.patterns = {k: _template_regex(v) for k, v in prof.commands.items()}

    def feed(self, data: bytes) -> bytes:
        self.inbuf += data
        return self._scpi() if self.prof.kind == "scpi" else self._modbus()

    def _reply(self, name: str, **kw) -> bytes:
        tpl = self.prof.replies.get(name, {"ack": "OK", "error": "ERR",
                                           "temp": "{temp_degC:.2f}"}.get(name, ""))
        return (tpl.format(**kw) + self.prof.terminator).encode()

    def _scpi(self) -> bytes:
        out = b""
        while True:
            m = re.search(rb"\r\n|\r|\n", self.inbuf)
            if not m:
                return out
            line = self.inbuf[:m.start()].decode("ascii", "replace").strip()
            self.inbuf = self.inbuf[m.end():]
            if not line:
                continue
            self.log.append(line)
            for name, pat in self.patterns.items():
                mm = pat.match(line)
                if not mm:
                    continue
                vals = {k: float(v) for k, v in mm.groupdict().items()}
                if name == "set_temp":
                    self.phys.setpoint = vals["temp_degC"]
                elif name == "set_ramp":
                    self.phys.set_rate(vals["rate_dpm"])
                elif name == "query_temp":
                    out += self._reply("temp", temp_degC=self.phys.air)
                    break
                out += self._reply("ack")
                break
            else:
                out += self._reply("error")

    def _modbus(self) -> bytes:
        from calib_cli.acquire import modbus

        mb = self.prof.modbus
        out = b""
        while len(self.inbuf) >= 8:
            fr, self.inbuf = self.inbuf[:8], self.inbuf[8:]
            if not modbus.check(fr) or fr[0] != int(mb["slave"]):
                self.log.append(("bad", fr.hex()))
                self.inbuf = b""  # resynchronise on the next request
                continue
            fn, addr = fr[1], int.from_bytes(fr[2:4], "big")
            val = int.from_bytes(fr[4:6], "big")
            self.log.append((fn, addr, val))
            scale = float(mb["scale_degC"])
            signed = mb.get("signed", True)
            if fn == modbus.WRITE_SINGLE and addr == int(mb["setpoint_register"]):
                self.phys.setpoint = (modbus.to_signed(val) if signed else val) * scale
                out += fr
            elif fn == modbus.WRITE_SINGLE and addr == mb.get("ramp_register"):
                self.phys.set_rate(val * float(mb["ramp_scale_dpm"]))
                out += fr
            elif fn == int(mb.get("temp_function", 3)) and addr == int(mb["temp_register"]) \
                    and val == 1:
                c = int(round(self.phys.air / scale)) & 0xFFFF
                out += modbus.frame(fr[0], fn, bytes([2]) + c.to_bytes(2, "big"))
            else:
                code = 1 if fn not in (3, 4, 6) else 2
                out += modbus.frame(fr[0], fn | 0x80, bytes([code]))
        return out


# ---------------------------------------------------------------------------
# pseudo-terminals


class PtyPort:
    """A pty whose slave is reachable through a stable symlink, so that a
    simulated disconnect (close, reopen) keeps the path the recorder uses."""

    def __init__(self, link: str):
        self.link = link
        self.master = self.slave = None
        self.out = bytearray()
        self.last_progress = time.monotonic()
        self.discarded = 0  # bytes thrown away while nobody read the port
        self.open()

    def open(self) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        os.set_blocking(self.master, False)
        tmp = self.link + ".new"
        if os.path.lexists(tmp):
            os.unlink(tmp)
        os.symlink(os.ttyname(self.slave), tmp)
        os.replace(tmp, self.link)

    def close(self) -> None:
        for fd in (self.master, self.slave):
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self.master = self.slave = None
        self.out.clear()

    def write(self, data: bytes) -> bool:
        """Queue bytes; False if the device FIFO is full (the frame is dropped)."""
        if len(self.out) + len(data) > FIFO_LIMIT:
            return False
        self.out += data
        return True

    def pump(self) -> None:
        """Write what the port takes. Like a real device, which does not keep
        its output for a port nobody has opened, the queue is dropped when
        nothing has been taken for STALL_S seconds (else a recorder started
        later would first get seconds of stale samples)."""
        if not self.out:
            self.last_progress = time.monotonic()
        while self.out and self.master is not None:
            try:
                n = os.write(self.master, self.out[:65536])
            except (BlockingIOError, InterruptedError, OSError):
                break
            del self.out[:n]
            self.last_progress = time.monotonic()
        if self.out and time.monotonic() - self.last_progress > STALL_S:
            self.discarded += len(self.out)
            self.out.clear()
            self.last_progress = time.monotonic()

    def read(self) -> bytes:
        if self.master is None:
            return b""
        try:
            return os.read(self.master, 4096)
        except (BlockingIOError, OSError):
            return b""


# ---------------------------------------------------------------------------


@dataclass
class Injected:
    corrupted: int = 0
    dropped: int = 0
    garbage_bursts: int = 0
    disconnect_frames: int = 0
    overflow: int = 0
    frames: int = 0
    samples: int = 0
    corrupted_seq: list = field(default_factory=list)
    dropped_seq: list = field(default_factory=list)
    overflow_seq: list = field(default_factory=list)  # frames the full FIFO lost

    @property
    def lost(self) -> int:
        return self.corrupted + self.dropped + self.disconnect_frames + self.overflow


class Emulator:
    """Run with ``start()`` (a thread) or ``run()``; ``stop()`` ends it.

    paths: {"imu": ..., "table": ...} symlinks to the pty slaves (serial
    profiles), or the CAN channel name in ``can_channel``.
    """

    def __init__(self, prof: ImuProfile, table: TableProfile | None = None,
                 truth: Truth | None = None, site: Site | None = None, rate: float | None = None,
                 faults: Faults | None = None, seed: int = 0, layout: Layout | None = None,
                 attitude_deg=(0.0, 0.0, 0.0), temp_c: float = 25.0, link_dir: str | None = None,
                 can_interface: str = "virtual", can_channel: str | None = None,
                 chunk_s: float = 0.005, chamber=None, chamber_tau: float = 300.0,
                 datagram: int = 0):
        site = site or Site()
        layout = layout or Layout()
        self.prof, self.site = prof, site
        self.fs = float(rate or prof.rate_hz)
        self.rng = np.random.default_rng(seed)
        self.seed = seed
        self._noise, self._noise_k = None, 0  # the truth's noise realisation, next sample
        self.truth = truth or default_truth(layout, self.rng)
        self.faults = faults or Faults()
        self.frng = np.random.default_rng(self.faults.seed)
        self.temp_c = temp_c
        self.chunk_s = chunk_s
        self.encoder = make_encoder(prof, datagram)
        self.responder = None
        if prof.format != "can" and (prof.configure or prof.start_steps or prof.stop_steps
                                     or prof.identify):
            from calib_cli.acquire.device import Responder

            self.responder = Responder(prof, self.fs)
        self.unit = VirtualUnit(site, self.fs, np.asarray(attitude_deg, float) * D2R,
                                table.speed_dps if table else 90.0)
        self.table = VirtualTable(table, self.unit) if table and table.kind == "serial" else None
        self.injected = Injected()
        self.k = 0
        self._stop = threading.Event()
        self._thread = None
        self.started = threading.Event()
        self.own_dir = link_dir is None
        self.dir = link_dir or tempfile.mkdtemp(prefix="calib-emu-")
        self.paths: dict[str, str] = {}
        self.bus = None
        self.imu_port = None
        self.table_port = None
        if prof.format == "can":
            import can

            self.can_channel = can_channel or f"calib-emu-{os.getpid()}-{id(self)}"
            self.bus = can.Bus(interface=can_interface, channel=self.can_channel,
                               receive_own_messages=False)
            self.paths["can"] = self.can_channel
        else:
            self.imu_port = PtyPort(os.path.join(self.dir, "imu"))
            self.paths["imu"] = self.imu_port.link
        if self.table is not None:
            self.table_port = PtyPort(os.path.join(self.dir, "table"))
            self.paths["table"] = self.table_port.link
        # a climatic chamber: the unit's temperature follows it (temp_c is the start)
        self.chamber = self.chamber_port = None
        if chamber is not None and chamber.kind != "manual":
            if self.truth.model.has("thermal_lag"):
                raise InputError("the emulator does not model thermal_lag (the truth file has "
                                 "it); leave it out", chamber.path)
            self.chamber_phys = ChamberPhysics(temp_c, chamber_tau, chamber.max_ramp_dpm, self.fs)
            self.chamber = VirtualChamber(chamber, self.chamber_phys)
            self.chamber_port = PtyPort(os.path.join(self.dir, "chamber"))
            self.paths["chamber"] = self.chamber_port.link
        self._disc = None  # (k_start, k_end) of the disconnect

    # -- values of one chunk -------------------------------------------------
    def samples(self, k0: int, n: int, temp: np.ndarray | None = None) -> dict:
        """The generator: SI outputs {"accel": (n, ns), "gyro": (n, ns)} of samples
        k0..k0+n-1 (in order; the noise realisation is stateful). The truth's noise
        (white, bias random walk, flicker) is realised by the model's effects with the
        seed, exactly as ``calib simulate`` does: the same truth and seed give the same
        samples bit for bit (tests/test_noise_effects.py). ``temp`` (n,) degC: the unit's
        temperature (a chamber's), else the constant start temperature."""
        if self._noise is None or k0 != self._noise_k:
            if k0 != 0:
                raise ValueError(f"samples are generated in order: next is {self._noise_k}, "
                                 f"asked for {k0}")
            model, params = self.truth.noise_model()
            self._noise = model.noise_realisation(params, self.fs, self.seed)
        if temp is None:
            temp = np.full(n, self.temp_c)
        kin = self.unit.kinematics(k0, n).with_(temp=temp)
        out = self.truth.model.predict(self.truth.params, kin)
        noise = self._noise.next(kin)
        self._noise_k = k0 + n
        return {s: out[s] + noise[s] for s in ("accel", "gyro")}

    def _values(self, k0: int, n: int) -> dict:
        temp = self.chamber_phys.advance(n) if self.chamber is not None else np.full(n, self.temp_c)
        ys = self.samples(k0, n, temp)
        p = self.prof
        vals = {}
        names = list(p.channels)
        nsens = self.truth.model.layout.n
        for s in ("accel", "gyro"):
            y = ys[s]
            chan = (["ax", "ay", "az"] if s == "accel" else ["gx", "gy", "gz"]) \
                if not p.redundant else [f"{s[0]}{i}" for i in range(nsens)]
            for j, c in enumerate(chan):
                vals[c] = y[:, j]
        if "temp" in names:
            vals["temp"] = temp
        fields = {f.name: f for f in p.all_fields()}
        raw = {c: (vals[c] / fields[c].unit_factor - fields[c].add) / fields[c].scale
               for c in names}
        ks = k0 + np.arange(n)
        if p.seq_field:
            raw[p.seq_field] = np.rint(ks * (p.seq_per_s / self.fs if p.seq_per_s else 1.0)) \
                % p.seq_modulus
        if p.time_field:
            t = ks / self.fs / p.time_scale
            if not fields[p.time_field].type.startswith("f"):
                t = np.rint(t)
            raw[p.time_field] = t % p.time_modulus
        return raw

    def _corrupt(self, frame: bytes) -> bytes:
        f = self.faults
        if f.corrupt_where == "payload":
            a, b = self.encoder.payload_span(frame)
        else:
            a, b = 0, len(frame) - (len(self.prof.terminator) if self.prof.format == "ascii"
                                    else 0)
        i = int(self.frng.integers(a, b))
        buf = bytearray(frame)
        if self.prof.format == "ascii" and f.corrupt_where == "payload":
            # a different printable character that cannot end or start a sentence
            pool = "0123456789ABCDEF" if buf[i] in b"0123456789ABCDEF" else "0123456789"
            pool = pool.replace(chr(buf[i]), "")
            buf[i] = ord(pool[int(self.frng.integers(len(pool)))])
        else:
            buf[i] ^= int(self.frng.integers(1, 256))
        return bytes(buf)

    def _emit(self, k0: int, n: int) -> None:
        raw = self._values(k0, n)
        frames = self.encoder.encode(raw)
        f, inj = self.faults, self.injected
        seqs = k0 + np.arange(n)
        out = bytearray()
        queued = []  # the counters of the frames in ``out``
        for i, fr in enumerate(frames):
            kk = int(seqs[i])
            inj.samples += 1
            if self._disc and self._disc[0] <= kk < self._disc[1]:
                inj.disconnect_frames += 1
                continue
            if f.drop and self.frng.random() < f.drop:
                inj.dropped += 1
                inj.dropped_seq.append(kk)
                continue
            if self.bus is not None:
                self._send_can(fr)
                inj.frames += 1
                continue
            if f.garbage and self.frng.random() < f.garbage:
                m = int(self.frng.integers(1, f.garbage_max + 1))
                out += self.frng.integers(0, 256, m, dtype=np.uint8).tobytes()
                inj.garbage_bursts += 1
            if f.corrupt and self.frng.random() < f.corrupt:
                fr = self._corrupt(fr)
                inj.corrupted += 1
                inj.corrupted_seq.append(kk)
            out += fr
            queued.append(kk)
            inj.frames += 1
        if out and self.imu_port is not None:
            if self.imu_port.master is None or not self.imu_port.write(bytes(out)):
                # the whole chunk lost (a recorder that falls behind on a loaded machine)
                inj.overflow += len(queued)
                inj.overflow_seq.extend(queued)
        if self.imu_port is not None:
            self.imu_port.pump()

    def _send_can(self, msgs) -> None:
        import can

        for cid, ext, data in msgs:
            self.bus.send(can.Message(arbitration_id=cid, is_extended_id=ext, data=data))

    # -- main loop -------------------------------------------------------------
    def run(self, duration: float | None = None) -> None:
        t0 = time.monotonic()
        self.started.set()
        f = self.faults
        while not self._stop.is_set():
            now = time.monotonic() - t0
            if duration is not None and now >= duration:
                break
            if self.table_port is not None:
                data = self.table_port.read()
                if data:
                    rep = self.table.feed(data, self.k)
                    self.table_port.write(rep)
                self.table_port.pump()
            if self.chamber_port is not None:
                data = self.chamber_port.read()
                if data:
                    self.chamber_port.write(self.chamber.feed(data))
                self.chamber_port.pump()
            if f.disconnect_at is not None and self.imu_port is not None:
                if self._disc is None and now >= f.disconnect_at:
                    k1 = self.k + int(round(f.disconnect_for * self.fs))
                    self._disc = (self.k, k1)
                    self.imu_port.close()
                elif self._disc and self.imu_port.master is None and self.k >= self._disc[1]:
                    self.imu_port.open()
            if self.responder is not None and self.imu_port is not None:
                data = self.imu_port.read()
                if data:  # the configuration exchange (acquire/device.py)
                    rep = self.responder.feed(data)
                    if rep:
                        self.imu_port.write(rep)
            due = int(now * self.fs) - self.k
            if due > 0 and self.responder is not None and not self.responder.streaming:
                self._values(self.k, due)  # stopped (configuration mode): nothing is sent
                self.k += due
                due = 0
            if due <= 0:
                if self.imu_port is not None:
                    self.imu_port.pump()
                time.sleep(min(self.chunk_s, 0.002))
                continue
            n = min(due, max(int(self.chunk_s * self.fs), 1) * 4)
            self._emit(self.k, n)
            self.k += n

    def start(self, duration: float | None = None) -> "Emulator":
        self._thread = threading.Thread(target=self.run, args=(duration,), daemon=True)
        self._thread.start()
        self.started.wait(5)
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5)
        for p in (self.imu_port, self.table_port, self.chamber_port):
            if p is not None:
                p.close()
        if self.bus is not None:
            self.bus.shutdown()
        if self.own_dir:
            shutil.rmtree(self.dir, ignore_errors=True)
