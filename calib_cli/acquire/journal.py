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

import contextlib
import errno
import json
import os
import struct
import time
import zlib

import numpy as np

from calib_cli.errors import InputError, OutputError

MAGIC = b"CALIBJ01"
_HDR = struct.Struct("<cI")
_U32 = struct.Struct("<I")
META_COLS = ("time", "seq", "segment")


class JournalWriter:
    def __init__(self, path: str, header: dict, flush_interval: float = 0.5):
        self.path = path
        try:  # never truncate an existing journal (a killed recording's data)
            self.fh = open(path, "xb", buffering=0)  # unbuffered: nothing left to flush
        except FileExistsError:
            raise InputError(f"a journal exists (an earlier recording?): recover it with "
                             f"`calib recover {path} --out FILE.h5`, or pass --force to set "
                             "it aside", path) from None
        except OSError as exc:
            raise OutputError(f"cannot create the journal: {exc.strerror}", path) from None
        blob = json.dumps(header).encode()
        self.flush_interval = flush_interval
        self.last_flush = time.monotonic()
        self.n_rows = 0
        self.flushed_rows = 0
        try:
            self._write(MAGIC + _U32.pack(len(blob)) + blob)
            self.sync()
        except BaseException:  # the file this call made holds no data: leave nothing behind
            self.fh.close()
            with contextlib.suppress(OSError):
                os.unlink(path)
            raise

    def _failed(self, exc: OSError):
        """A full disk (or an I/O error) while recording: exit 2 naming the journal,
        which keeps what reached the disk (issue 37: was exit 3 "No space left on
        device", naming nothing)."""
        what = ("disk full" if exc.errno in (errno.ENOSPC, errno.EDQUOT)
                else f"cannot write ({exc.strerror or exc})")
        if not self.n_rows:
            return OutputError(f"{what} while recording: nothing was recorded", self.path)
        return OutputError(f"{what} while recording; the journal keeps what reached the disk "
                           f"(calib recover {self.path} --out FILE.h5)", self.path)

    def _write(self, data: bytes) -> None:
        mv = memoryview(data)
        try:
            while len(mv):
                mv = mv[self.fh.write(mv):]
        except OSError as exc:
            raise self._failed(exc) from None

    def _record(self, kind: bytes, payload: bytes) -> None:
        self._write(_HDR.pack(kind, len(payload)) + payload + _U32.pack(zlib.crc32(payload)))

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
        try:
            self.fh.flush()
            os.fsync(self.fh.fileno())
        except OSError as exc:
            raise self._failed(exc) from None
        self.last_flush = time.monotonic()
        self.flushed_rows = self.n_rows

    def close(self, counts: dict | None = None) -> None:
        try:
            if counts is not None:
                self.counters(counts)
            self.sync()
        finally:
            self.fh.close()


def _valid_at(data: bytes, pos: int, ncols: int):
    """The end of a whole record with a good CRC starting at ``pos``, or None."""
    if pos + _HDR.size > len(data):
        return None
    kind, ln = _HDR.unpack_from(data, pos)
    if kind not in (b"S", b"C"):
        return None
    end = pos + _HDR.size + ln + 4
    if end > len(data):
        return None
    payload = data[pos + _HDR.size:pos + _HDR.size + ln]
    if kind == b"S":
        if ln < 8:
            return None
        k, c = struct.unpack_from("<II", payload)
        if c != ncols or 8 + 8 * k * c != ln:
            return None
    if zlib.crc32(payload) != _U32.unpack_from(data, end - 4)[0]:
        return None
    return end


def _resync(data: bytes, pos: int, ncols: int):
    """The start of the next valid record after a damaged one, or None."""
    q = pos + 1
    while q < len(data):
        nxt = [i for i in (data.find(b"S", q), data.find(b"C", q)) if i >= 0]
        if not nxt:
            return None
        q = min(nxt)
        if _valid_at(data, q, ncols) is not None:
            return q
        q += 1
    return None


def read_journal(path: str) -> tuple[dict, np.ndarray, dict, bool]:
    """(header, rows, last counters, complete) from a journal. ``complete`` is
    True only when the recorder closed it (its last record is the closing
    counters, which carry ``plan_finished``) and nothing in it is damaged. A
    damaged record is skipped and reading resynchronises on the next valid
    one; the counters then hold ``journal_records_skipped`` and
    ``journal_bytes_skipped``."""
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
    parts, counters, damaged = [], {}, False
    closed = False
    skipped = skipped_bytes = 0
    if not isinstance(header, dict) or not isinstance(header.get("channels", []), list):
        raise InputError("journal header is damaged", p)
    ncols = len(META_COLS) + len(header.get("channels", []))
    while pos < len(data):
        end = _valid_at(data, pos, ncols)
        if end is None:
            damaged = True
            nxt = _resync(data, pos, ncols)
            if nxt is None:  # a cut tail (killed recorder) or damage to the end
                if pos + _HDR.size <= len(data) and data[pos:pos + 1] in (b"S", b"C") and \
                        pos + _HDR.size + _HDR.unpack_from(data, pos)[1] + 4 > len(data):
                    break  # the last record was cut short: not counted as damage
                skipped += 1
                skipped_bytes += len(data) - pos
                break
            skipped += 1
            skipped_bytes += nxt - pos
            pos = nxt
            continue
        kind, ln = _HDR.unpack_from(data, pos)
        payload = data[pos + _HDR.size:pos + _HDR.size + ln]
        if kind == b"S":
            k, c = struct.unpack_from("<II", payload)
            parts.append(np.frombuffer(payload, "<f8", k * c, 8).reshape(k, c))
            closed = False
        else:
            try:
                counters = json.loads(payload)
            except ValueError:
                counters = {}
            closed = isinstance(counters, dict) and "plan_finished" in counters
        pos = end
    complete = closed and not damaged
    if not isinstance(counters, dict):
        counters = {}
    counters = dict(counters)
    if skipped:
        counters["journal_records_skipped"] = skipped
        counters["journal_bytes_skipped"] = skipped_bytes
    rows = np.concatenate(parts) if parts else np.empty((0, ncols))
    return header, rows, counters, complete
