"""Decoders: bytes (or CAN messages) -> samples in SI units, with exact loss counts.

A decoder turns the byte stream into *items*: a tuple of raw field values
(profile field order) for each frame whose checksum holds, or ``None`` for a
frame rejected by its checksum. It resynchronises by itself: after garbage,
a partial frame or a bad checksum it searches for the next sync bytes (or
sentence start) one byte further on, so one damaged frame never takes its
neighbours with it.

``SampleStream`` turns items into samples and keeps the counts. Between two
accepted frames the sequence counter tells how many frames are missing (m);
the r rejected frames seen in between are the reason for min(r, m) of them
(checksum errors), the rest are gaps (dropped frames). A rejected "frame"
that has no missing sequence number behind it (a false sync inside garbage)
is counted apart as ``spurious_rejects``. So each lost frame is counted
exactly once, and checksum errors + gaps = missing sequence numbers.

The encoders live in ``emulator.py`` and are written separately; the tests
check these decoders against golden byte vectors written by hand.
"""

from __future__ import annotations

import struct

import numpy as np

from calib_cli.acquire.profile import TYPE_SIZE, TYPES, ImuProfile, Layout

MAX_SENTENCE = 1024  # an ASCII sentence longer than this is garbage


def field_reader(fields, byte_order: str):
    """A function (buf, offset) -> tuple of the fields' raw values, packed in
    order from ``offset``; 24-bit integers (STIM300, two's complement) are
    unpacked apart from the struct module."""
    bo = "<" if byte_order == "little" else ">"
    fmt = bo + "".join(TYPES[f.type] or "3s" for f in fields)
    st = struct.Struct(fmt)
    odd = [(i, f.type == "i24") for i, f in enumerate(fields) if TYPES[f.type] is None]
    if not odd:
        return st.unpack_from, st.size
    order = byte_order

    def read(buf, off):
        v = list(st.unpack_from(buf, off))
        for i, signed in odd:
            v[i] = int.from_bytes(v[i], order, signed=signed)
        return v
    return read, st.size


class _Frame:
    """The decoding plan of one layout."""

    def __init__(self, prof: ImuProfile, lay: Layout, index: dict):
        self.sync, self.end = lay.sync, lay.end
        self.n_cs = prof.checksum.nbytes
        self.len_struct = (struct.Struct(("<" if lay.length_order == "little" else ">")
                                         + TYPES[lay.length_type]) if lay.length_type else None)
        self.hdr = len(self.sync) + (self.len_struct.size if self.len_struct else 0)
        self.len_extra = self.n_cs if lay.length_covers != "payload" else 0
        self.tagged = lay.tagged
        self.nfields = len(index)
        if self.tagged is None:
            self.read, self.psize = field_reader(lay.fields, prof.byte_order)
            self.pos = [index[f.name] for f in lay.fields]
            self.fixed_len = self.psize + self.len_extra
        else:
            tg = self.tagged
            ib = "<" if tg.byte_order == "little" else ">"
            self.id_struct = struct.Struct(ib + TYPES[tg.id_type])
            self.ln_struct = struct.Struct(ib + TYPES[tg.length_type])
            self.tags = {}
            for tag in dict.fromkeys(f.tag for f in lay.fields):
                fl = [f for f in lay.fields if f.tag == tag]
                readers = [(index[f.name], field_reader((f,), prof.byte_order)[0], f.offset,
                            TYPE_SIZE[f.type]) for f in fl]
                self.tags[tag] = readers
            self.required = {index[f.name] for f in lay.fields if not f.optional}
            self.psize = None
            self.fixed_len = None
        self.missing = [i for i in range(self.nfields)]
        self.min_size = self.hdr + (self.psize or 0) + self.n_cs + len(self.end)

    def payload_len(self, buf, i) -> int | None:
        """Payload bytes of the frame at i (None: the length field is implausible)."""
        if self.len_struct is None:
            return self.psize
        n = self.len_struct.unpack_from(buf, i + len(self.sync))[0] - self.len_extra
        if self.fixed_len is not None:
            return self.psize if n + self.len_extra == self.fixed_len else None
        return n if n >= 0 else None

    def decode(self, buf, a: int, n: int):
        """The item (a list over the profile's fields, NaN where absent) of the
        payload buf[a:a+n], or None when it cannot be what the profile says."""
        out = [float("nan")] * self.nfields
        if self.tagged is None:
            for k, v in zip(self.pos, self.read(buf, a), strict=True):
                out[k] = v
            return out
        tg, end, seen = self.tagged, a + n, set()
        isz, lsz = self.id_struct.size, self.ln_struct.size
        p = a
        while p < end:
            if p + isz + lsz > end:
                return None
            if tg.order == "id-length":
                rid = self.id_struct.unpack_from(buf, p)[0]
                ln = self.ln_struct.unpack_from(buf, p + isz)[0]
            else:
                ln = self.ln_struct.unpack_from(buf, p)[0]
                rid = self.id_struct.unpack_from(buf, p + lsz)[0]
            if tg.length_includes_header:
                ln -= isz + lsz
            data = p + isz + lsz
            if ln < 0 or data + ln > end:
                return None
            for k, read, off, size in self.tags.get(rid, ()):
                if off + size <= ln:
                    out[k] = read(buf, data + off)[0]
                    seen.add(k)
            p = data + ln
        if not self.required <= seen:
            return None
        return out


class BinaryDecoder:
    """Sync bytes | optional length | payload (fixed fields or tagged records) |
    checksum | end bytes. Several layouts (datagrams whose identifier decides
    the content) are tried at each sync."""

    def __init__(self, prof: ImuProfile):
        index = {f.name: i for i, f in enumerate(prof.fields)}
        self.frames = [_Frame(prof, lay, index) for lay in prof.layouts]
        self.single = self.frames[0] if len(self.frames) == 1 else None
        self.cs = prof.checksum
        self.buf = bytearray()
        self.garbage_bytes = 0
        self.keep = max(len(f.sync) for f in self.frames) - 1

    def _find(self, buf, pos):
        if self.single is not None:
            return buf.find(self.single.sync, pos), self.single
        best, fr = -1, None
        for f in self.frames:
            i = buf.find(f.sync, pos)
            if i >= 0 and (best < 0 or i < best):
                best, fr = i, f
        return best, fr

    def feed(self, data: bytes) -> list:
        buf = self.buf
        buf += data
        out = []
        pos, n = 0, len(buf)
        cs = self.cs
        while True:
            i, fr = self._find(buf, pos)
            if i < 0:
                keep = max(pos, n - self.keep)
                self.garbage_bytes += keep - pos
                pos = keep
                break
            self.garbage_bytes += i - pos
            if n - i < fr.hdr:
                pos = i
                break
            plen = fr.payload_len(buf, i)
            if plen is None or plen > 65536:
                pos = i + 1  # a false sync or a damaged length: look further on
                self.garbage_bytes += 1
                continue
            size = fr.hdr + plen + fr.n_cs + len(fr.end)
            if n - i < size:
                pos = i
                break
            body_end = i + fr.hdr + plen
            if fr.n_cs:
                a = i + cs.start(len(fr.sync), fr.hdr)
                want = int.from_bytes(buf[body_end:body_end + fr.n_cs], cs.byte_order)
                if cs.compute(bytes(buf[a:body_end])) != want:
                    out.append(None)
                    pos = i + 1
                    self.garbage_bytes += 1
                    continue
            if fr.end and buf[body_end + fr.n_cs:i + size] != fr.end:
                out.append(None)
                pos = i + 1
                self.garbage_bytes += 1
                continue
            item = fr.decode(buf, i + fr.hdr, plen)
            out.append(item)  # None: good checksum, content not as the profile says
            pos = i + size if item is not None else i + 1
        del buf[:pos]
        return out


class AsciiDecoder:
    """START body SEPARATOR XX [terminator], or START body TERMINATOR without a
    checksum. The body is split by the delimiter (or matched by the pattern)."""

    def __init__(self, prof: ImuProfile):
        self.prof = prof
        self.start = prof.start.encode()
        self.sep = prof.separator.encode()
        self.term = prof.terminator.encode()
        self.cs = prof.checksum
        self.nhex = prof.hex_digits if self.cs.kind != "none" else 0
        self.fields = prof.fields
        self.buf = bytearray()
        self.garbage_bytes = 0

    def _parse(self, body: bytes):
        try:
            text = body.decode("ascii")
        except UnicodeDecodeError:
            return None
        if self.prof.pattern is not None:
            m = self.prof.pattern.fullmatch(text)
            if m is None:
                return None
            try:
                return tuple(0.0 if f.literal is not None else float(m.group(f.name))
                             for f in self.fields)
            except ValueError:
                return None
        toks = text.split(self.prof.delimiter)
        if len(toks) != len(self.fields):
            return None
        out = []
        for f, tok in zip(self.fields, toks, strict=True):
            if f.literal is not None:
                if tok != f.literal:
                    return None
                out.append(0.0)
            else:
                try:
                    out.append(float(tok))
                except ValueError:
                    return None
        return tuple(out)

    def feed(self, data: bytes) -> list:
        buf = self.buf
        buf += data
        out = []
        pos, n = 0, len(buf)
        end_mark = self.sep if self.nhex else self.term
        while True:
            i = buf.find(self.start, pos)
            if i < 0:
                self.garbage_bytes += n - pos
                pos = n
                break
            self.garbage_bytes += i - pos
            j = buf.find(end_mark, i + 1)
            nxt = buf.find(self.start, i + 1)
            if j < 0:
                if nxt >= 0 or n - i > MAX_SENTENCE:  # a broken sentence: skip to the next
                    self.garbage_bytes += (nxt if nxt >= 0 else n) - i
                    pos = nxt if nxt >= 0 else n
                    continue
                pos = i
                break
            if 0 <= nxt < j:  # a new sentence starts before this one ended
                self.garbage_bytes += nxt - i
                pos = nxt
                continue
            body = bytes(buf[i + 1:j])
            if self.nhex:
                if n - (j + 1) < self.nhex:
                    pos = i
                    break
                if 0 <= nxt < j + 1 + self.nhex:  # a sentence starts inside the digits
                    self.garbage_bytes += nxt - i
                    pos = nxt
                    continue
                hx = bytes(buf[j + 1:j + 1 + self.nhex])
                pos = j + 1 + self.nhex
                try:
                    want = int(hx, 16)
                    ok = all(c in b"0123456789abcdefABCDEF" for c in hx)
                except ValueError:
                    ok = False
                if not ok or self.cs.compute(body) != want:
                    out.append(None)
                    continue
            else:
                pos = j + len(self.term)
            item = self._parse(body)
            out.append(item)  # a sentence with a good checksum but bad content: rejected
        del buf[:pos]
        return out


class CanAssembler:
    """CAN messages -> items: a sample is complete when every message of the
    profile has arrived with the same counter value (without a counter: when
    each message has arrived once since the last sample). Messages of a DBC
    profile are decoded by cantools (scale and offset from the DBC file)."""

    def __init__(self, prof: ImuProfile):
        self.prof = prof
        self.msgs = {m.can_id: m for m in prof.messages}
        bo = "<" if prof.byte_order == "little" else ">"
        from calib_cli.acquire.candbc import CAN_TYPES

        self.structs = {m.can_id: [(f.name, struct.Struct(bo + CAN_TYPES[f.type]), f.offset)
                                   for f in m.fields] for m in prof.messages
                        if m.dbc_name is None}
        self.names = [f.name for f in prof.all_fields()]
        self.seq = prof.seq_field
        self.partial: dict = {}
        self.garbage_bytes = 0
        self.foreign = 0

    def _values(self, m, data: bytes) -> dict | None:
        if m.dbc_name is not None:
            try:
                sig = self.prof.dbc.decode_message(m.can_id, bytes(data), scaling=True,
                                                   decode_choices=False)
            except Exception:  # noqa: BLE001 - a frame cantools cannot decode
                return None
            return {f.name: float(sig[f.literal]) for f in m.fields}
        return {name: st.unpack_from(data, off)[0] for name, st, off in self.structs[m.can_id]}

    def feed_message(self, can_id: int, data: bytes) -> list:
        m = self.msgs.get(can_id)
        if m is None:
            self.foreign += 1
            return []
        if len(data) < m.length:
            return [None]
        if m.checksum.nbytes:
            k = m.length - m.checksum.nbytes
            want = int.from_bytes(data[k:m.length], m.checksum.byte_order)
            if m.checksum.compute(bytes(data[:k])) != want:
                return [None]
        vals = self._values(m, data)
        if vals is None:
            return [None]
        c = vals[self.seq] if self.seq else None
        lost = []
        if self.seq is None and can_id in self.partial.get(None, {}):
            self.partial = {}  # a message repeats before its partner came: a sample was lost
            lost = [None]
        part = self.partial.setdefault(c, {})
        part[can_id] = vals
        if len(part) < len(self.msgs):
            return lost
        merged = {}
        for v in part.values():
            merged.update(v)
        self.partial = {}  # older incomplete samples can no longer complete
        return lost + [tuple(merged[n] for n in self.names)]


def make_decoder(prof: ImuProfile):
    return {"binary": BinaryDecoder, "ascii": AsciiDecoder, "can": CanAssembler}[prof.format](prof)


COUNTERS = ("frames", "checksum_errors", "gaps", "spurious_rejects", "duplicates",
            "disconnects", "garbage_bytes")


class SampleStream:
    """Items -> rows [time_s, seq_unwrapped, channels in SI...] with exact counts.

    Time: from the device counter (unwrapped over rollovers), from the
    sequence counter / rate_hz, or from the host clock at arrival. The sequence
    counter may count frames (1 a frame) or a clock (``counts_per_s``: the
    frames between two values are the difference times rate / counts_per_s).
    An optional field missing from a frame (NaN) keeps its last value.
    """

    def __init__(self, prof: ImuProfile):
        self.prof = prof
        names = [f.name for f in prof.all_fields()]
        fields = prof.all_fields()
        self.ch_idx = [names.index(c) for c in prof.channels]
        self.factors = np.array([fields[i].factor for i in self.ch_idx])
        self.adds = np.array([fields[i].add * fields[i].unit_factor for i in self.ch_idx])
        self.hold = [j for j, i in enumerate(self.ch_idx) if fields[i].optional]
        self.last_vals = [float("nan")] * len(self.ch_idx)
        self.seq_idx = names.index(prof.seq_field) if prof.seq_field else None
        self.mod = prof.seq_modulus
        self.per_frame = prof.seq_per_frame
        self.time_idx = names.index(prof.time_field) if prof.time_field else None
        self.tmod = prof.time_modulus
        self.counts = dict.fromkeys(COUNTERS, 0)
        self.pending = 0  # rejects since the last accepted frame
        self.last_seq = None
        self.useq = 0
        self.last_traw = None
        self.tcount = 0
        self.t0_host = None
        self.last_host = None
        self.gap_host_dt = None  # set after a reconnect: resolves counter rollovers
        self.useq0 = None

    @property
    def n_channels(self) -> int:
        return len(self.ch_idx)

    def mark_disconnect(self) -> None:
        self.counts["disconnects"] += 1
        self.gap_host_dt = 0.0

    def _frames_between(self, s) -> int:
        """Frames from the last accepted counter value to ``s`` (0: a duplicate)."""
        d = (s - self.last_seq) % self.mod
        if self.gap_host_dt:  # after a disconnect the counter may have wrapped
            k = round((self.gap_host_dt * self.prof.rate_hz * self.per_frame - d) / self.mod)
            d += max(k, 0) * self.mod
            self.gap_host_dt = None
        return int(round(d / self.per_frame))

    def push(self, items: list, host_time: float) -> np.ndarray:
        """Rows (k, 2 + channels) for the accepted frames among ``items``."""
        if self.t0_host is None:
            self.t0_host = host_time
        if self.gap_host_dt is not None and self.last_host is not None:
            self.gap_host_dt = host_time - self.last_host
        rate = self.prof.rate_hz
        rows_raw, rows_meta = [], []
        c = self.counts
        for it in items:
            if it is None:
                self.pending += 1
                continue
            if self.seq_idx is not None:
                s = it[self.seq_idx]
                if s != s:  # NaN: a counter the frame lacks
                    self.pending += 1
                    continue
                if self.last_seq is None:
                    first = int(s) if self.per_frame == 1 and float(s).is_integer() else 0
                    self.useq = self.useq0 = first
                    self.counts["spurious_rejects"] += self.pending
                else:
                    d = self._frames_between(s)
                    if d <= 0:
                        c["duplicates"] += 1
                        self.pending = 0
                        continue
                    m = d - 1
                    ce = min(self.pending, m)
                    c["checksum_errors"] += ce
                    c["gaps"] += m - ce
                    c["spurious_rejects"] += self.pending - ce
                    self.useq += d
                self.last_seq = s
            else:
                c["checksum_errors"] += self.pending
                self.useq += 1
                if self.useq0 is None:
                    self.useq0 = self.useq
            self.pending = 0
            c["frames"] += 1
            if self.time_idx is not None:
                traw = it[self.time_idx]
                if self.last_traw is not None:
                    self.tcount += (traw - self.last_traw) % self.tmod
                self.last_traw = traw
                t = self.tcount * self.prof.time_scale
            elif self.prof.time_source == "sequence":
                t = (self.useq - self.useq0) / rate
            else:
                t = host_time - self.t0_host
            rows_meta.append((t, self.useq))
            row = [it[i] for i in self.ch_idx]
            for j in self.hold:
                if row[j] != row[j]:
                    row[j] = self.last_vals[j]
                else:
                    self.last_vals[j] = row[j]
            rows_raw.append(row)
        self.last_host = host_time
        if not rows_raw:
            return np.empty((0, 2 + len(self.ch_idx)))
        out = np.empty((len(rows_raw), 2 + len(self.ch_idx)))
        out[:, :2] = rows_meta
        out[:, 2:] = np.asarray(rows_raw, dtype=float) * self.factors + self.adds
        return out
