"""The append-only journal of a recording: what survives a killed recorder.

Layout: the magic ``CALIBJ01``, a u32 length and a JSON header (profile,
plan text, channels), then records ``type (1 byte) | u32 length | payload |
u32 CRC-32 of the payload``. Types: ``S`` samples (u32 rows, u32 columns,
float64 little-endian rows: time, seq, segment, channels...), ``C`` the
counters (JSON). The writer flushes and fsyncs at least once a second; a
reader takes every whole record with a good CRC and stops at the first
damaged or cut one, so after SIGKILL or a power loss everything up to the
last flush comes back.
"""

from __future__ import annotations

import json
import os
import struct
import time
import zlib

import numpy as np

from calib_cli.errors import InputError

MAGIC = b"CALIBJ01"
_HDR = struct.Struct("<cI")
_U32 = struct.Struct("<I")
META_COLS = ("time", "seq", "segment")


class JournalWriter:
    def __init__(self, path: str, header: dict, flush_interval: float = 0.5):
        self.path = path
        self.fh = open(path, "wb")
        blob = json.dumps(header).encode()
        self.fh.write(MAGIC + _U32.pack(len(blob)) + blob)
        self.flush_interval = flush_interval
        self.last_flush = time.monotonic()
        self.n_rows = 0
        self.flushed_rows = 0
        self.sync()

    def _record(self, kind: bytes, payload: bytes) -> None:
        self.fh.write(_HDR.pack(kind, len(payload)) + payload
                      + _U32.pack(zlib.crc32(payload)))

    def append(self, rows: np.ndarray) -> None:
        if len(rows):
            rows = np.ascontiguousarray(rows, dtype="<f8")
            self._record(b"S", struct.pack("<II", *rows.shape) + rows.tobytes())
            self.n_rows += len(rows)

    def counters(self, counts: dict) -> None:
        self._record(b"C", json.dumps(counts).encode())

    def maybe_flush(self, counts: dict | None = None) -> bool:
        if time.monotonic() - self.last_flush >= self.flush_interval:
            if counts is not None:
                self.counters(counts)
            self.sync()
            return True
        return False

    def sync(self) -> None:
        self.fh.flush()
        os.fsync(self.fh.fileno())
        self.last_flush = time.monotonic()
        self.flushed_rows = self.n_rows

    def close(self, counts: dict | None = None) -> None:
        if counts is not None:
            self.counters(counts)
        self.sync()
        self.fh.close()


def read_journal(path: str) -> tuple[dict, np.ndarray, dict, bool]:
    """(header, rows, last counters, complete) from a journal; ``complete`` is
    False when the file ends in a cut or damaged record (a killed recorder)."""
    p = str(path)
    try:
        data = open(p, "rb").read()
    except FileNotFoundError:
        raise InputError("no such file", p) from None
    except OSError as exc:
        raise InputError(f"cannot read journal: {exc}", p) from None
    if not data.startswith(MAGIC) or len(data) < len(MAGIC) + 4:
        raise InputError("not a calib journal (bad magic)", p)
    n = _U32.unpack_from(data, len(MAGIC))[0]
    pos = len(MAGIC) + 4
    try:
        header = json.loads(data[pos:pos + n])
    except ValueError:
        raise InputError("journal header is damaged", p) from None
    pos += n
    parts, counters, complete = [], {}, True
    ncols = len(META_COLS) + len(header.get("channels", []))
    while pos < len(data):
        if pos + _HDR.size > len(data):
            complete = False
            break
        kind, ln = _HDR.unpack_from(data, pos)
        end = pos + _HDR.size + ln + 4
        if end > len(data):
            complete = False
            break
        payload = data[pos + _HDR.size:pos + _HDR.size + ln]
        if zlib.crc32(payload) != _U32.unpack_from(data, end - 4)[0]:
            complete = False
            break
        if kind == b"S":
            k, c = struct.unpack_from("<II", payload)
            if c != ncols:
                raise InputError(f"journal record has {c} columns, header says {ncols}", p)
            parts.append(np.frombuffer(payload, "<f8", k * c, 8).reshape(k, c))
        elif kind == b"C":
            counters = json.loads(payload)
        pos = end
    rows = np.concatenate(parts) if parts else np.empty((0, ncols))
    return header, rows, counters, complete
