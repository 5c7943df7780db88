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

from calib_cli.acquire.profile import TYPES, ImuProfile

MAX_SENTENCE = 1024  # an ASCII sentence longer than this is garbage


class BinaryDecoder:
    """Sync bytes | optional length | payload | checksum."""

    def __init__(self, prof: ImuProfile):
        self.sync = prof.sync
        self.payload = prof.payload_struct()
        bo = "<" if prof.byte_order == "little" else ">"
        self.len_struct = struct.Struct(bo + TYPES[prof.length_type]) if prof.length_type else None
        self.cs = prof.checksum
        n_cs = self.cs.nbytes
        self.expected_len = self.payload.size + (n_cs if prof.length_covers != "payload" else 0)
        self.hdr = len(self.sync) + (self.len_struct.size if self.len_struct else 0)
        self.size = self.hdr + self.payload.size + n_cs
        self.n_cs = n_cs
        self.cs_order = self.cs.byte_order
        self.buf = bytearray()
        self.garbage_bytes = 0

    def feed(self, data: bytes) -> list:
        buf = self.buf
        buf += data
        out = []
        pos, n, sync, size, hdr = 0, len(buf), self.sync, self.size, self.hdr
        cs, n_cs, covers = self.cs, self.n_cs, self.cs.covers
        unpack = self.payload.unpack_from
        while True:
            i = buf.find(sync, pos)
            if i < 0:
                keep = max(pos, n - len(sync) + 1)
                self.garbage_bytes += keep - pos
                pos = keep
                break
            self.garbage_bytes += i - pos
            if n - i < size:
                pos = i
                if n - i >= hdr and self.len_struct is not None:
                    if self.len_struct.unpack_from(buf, i + len(sync))[0] != self.expected_len:
                        pos = i + 1  # a false sync or a damaged length: look further on
                        self.garbage_bytes += 1
                        continue
                break
            if self.len_struct is not None and \
                    self.len_struct.unpack_from(buf, i + len(sync))[0] != self.expected_len:
                pos = i + 1
                self.garbage_bytes += 1
                continue
            if n_cs:
                end = i + size - n_cs
                a = i if covers == "all" else (i + len(sync) if covers == "after_sync" else i + hdr)
                want = int.from_bytes(buf[end:end + n_cs], self.cs_order)
                if cs.compute(bytes(buf[a:end])) != want:
                    out.append(None)
                    pos = i + 1
                    self.garbage_bytes += 1
                    continue
            out.append(unpack(buf, i + hdr))
            pos = i + size
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
    profile has arrived with the same counter value."""

    def __init__(self, prof: ImuProfile):
        self.prof = prof
        self.msgs = {m.can_id: m for m in prof.messages}
        bo = "<" if prof.byte_order == "little" else ">"
        self.structs = {m.can_id: [(f.name, struct.Struct(bo + TYPES[f.type]), f.offset)
                                   for f in m.fields] for m in prof.messages}
        self.names = [f.name for f in prof.all_fields()]
        self.seq = prof.seq_field
        self.partial: dict[int, dict] = {}
        self.garbage_bytes = 0
        self.foreign = 0

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
        vals = {name: st.unpack_from(data, off)[0] for name, st, off in self.structs[can_id]}
        c = vals[self.seq]
        part = self.partial.setdefault(c, {})
        part[can_id] = vals
        if len(part) < len(self.msgs):
            return []
        merged = {}
        for v in part.values():
            merged.update(v)
        self.partial = {}  # older incomplete samples can no longer complete
        return [tuple(merged[n] for n in self.names)]


def make_decoder(prof: ImuProfile):
    return {"binary": BinaryDecoder, "ascii": AsciiDecoder, "can": CanAssembler}[prof.format](prof)


COUNTERS = ("frames", "checksum_errors", "gaps", "spurious_rejects", "duplicates",
            "disconnects", "garbage_bytes")


class SampleStream:
    """Items -> rows [time_s, seq_unwrapped, channels in SI...] with exact counts.

    Time: from the device counter (unwrapped over rollovers), from the
    sequence counter / rate_hz, or from the host clock at arrival.
    """

    def __init__(self, prof: ImuProfile):
        self.prof = prof
        names = [f.name for f in prof.all_fields()]
        fields = prof.all_fields()
        self.ch_idx = [names.index(c) for c in prof.channels]
        self.factors = np.array([fields[i].factor for i in self.ch_idx])
        self.seq_idx = names.index(prof.seq_field) if prof.seq_field else None
        self.mod = 1 << prof.seq_bits
        self.time_idx = names.index(prof.time_field) if prof.time_field else None
        self.tmod = 1 << prof.time_bits
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
                s = int(it[self.seq_idx])
                if self.last_seq is None:
                    self.useq = self.useq0 = s
                    self.counts["spurious_rejects"] += self.pending
                else:
                    d = (s - self.last_seq) % self.mod
                    if d == 0:
                        c["duplicates"] += 1
                        self.pending = 0
                        continue
                    if self.gap_host_dt:  # after a disconnect the counter may have wrapped
                        k = round((self.gap_host_dt * rate - d) / self.mod)
                        d += max(k, 0) * self.mod
                        self.gap_host_dt = None
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
                traw = int(it[self.time_idx])
                if self.last_traw is not None:
                    self.tcount += (traw - self.last_traw) % self.tmod
                self.last_traw = traw
                t = self.tcount * self.prof.time_scale
            elif self.prof.time_source == "sequence":
                t = (self.useq - self.useq0) / rate
            else:
                t = host_time - self.t0_host
            rows_meta.append((t, self.useq))
            rows_raw.append([it[i] for i in self.ch_idx])
        self.last_host = host_time
        if not rows_raw:
            return np.empty((0, 2 + len(self.ch_idx)))
        out = np.empty((len(rows_raw), 2 + len(self.ch_idx)))
        out[:, :2] = rows_meta
        out[:, 2:] = np.asarray(rows_raw, dtype=float) * self.factors
        return out
