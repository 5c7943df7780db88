"""A streaming reader of PX4 ULog files (docs.px4.io "ULog File Format"),
memory flat in the log's length (docs/import.md).

The file is a 16-byte header (magic ``ULog\\x01\\x12\\x35``, version, start
time in us), a definitions section (flag bits 'B', formats 'F', information
'I'/'M', parameters 'P', default parameters 'Q') and a data section
(subscriptions 'A', data 'D', parameter changes 'P', dropouts 'O', sync 'S',
log strings 'L'/'C', unsubscriptions 'R'); every message is ``uint16 size,
uint8 type, payload``. The data section is read in blocks; one pass over a
block's message headers (the only per-message Python step) notes where the
wanted topics' records are, then each topic's records are gathered into one
numpy structured array (fields named as pyulog names them: arrays as
``name[i]``, nested types as ``name.field``). Memory: one block and its
records, whatever the log's length.

Damage is handled as pyulog does: a data message shorter than its format is
skipped, an unknown message type is corruption and the reader resumes after
the next sync message; a log cut in the middle of a message ends at the last
whole message (``truncated_bytes``).
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from calib_cli.errors import InputError

MAGIC = b"ULog\x01\x12\x35"
SYNC = bytes([0x2F, 0x73, 0x13, 0x20, 0x25, 0x0C, 0xBB, 0x12])
BLOCK = 1 << 21
MAX_MSG = 3 + 65535  # the longest message: what a block may carry over
TYPES = {"int8_t": "i1", "uint8_t": "u1", "int16_t": "<i2", "uint16_t": "<u2",
         "int32_t": "<i4", "uint32_t": "<u4", "int64_t": "<i8", "uint64_t": "<u8",
         "float": "<f4", "double": "<f8", "bool": "i1", "char": "i1"}
_VALUE = {"int32_t": "<i", "float": "<f", "uint8_t": "<B", "int8_t": "<b", "uint32_t": "<I",
          "int64_t": "<q", "uint64_t": "<Q", "double": "<d", "int16_t": "<h", "uint16_t": "<H"}
KNOWN = set(b"ABCDFILMOPQRS")


def _windows(buf, n: int):
    """gather(offsets, size) -> (m, size) uint8 copy of the records at ``offsets``
    of buf[:n], through a sliding-window view (no index array of m x size)."""
    arr = np.frombuffer(buf, np.uint8, n)
    views: dict = {}

    def gather(offsets, size):
        if size not in views:
            views[size] = np.lib.stride_tricks.sliding_window_view(arr, size)
        return views[size][np.asarray(offsets, dtype=np.intp)]

    return gather


def _kv(payload: bytes, off: int = 0) -> tuple[str, str, bytes]:
    """(type, name, value bytes) of an information or parameter message."""
    n = payload[off]
    key = payload[off + 1:off + 1 + n].decode("utf-8", "replace")
    typ, _, name = key.partition(" ")
    return typ, name, payload[off + 1 + n:]


def _value(typ: str, raw: bytes):
    if typ in _VALUE:
        size = struct.calcsize(_VALUE[typ])
        if len(raw) >= size:
            return struct.unpack_from(_VALUE[typ], raw)[0]
        return None
    if typ.startswith("char["):
        return raw.split(b"\0", 1)[0].decode("utf-8", "replace")
    return None


class ULogReader:
    """One ULog file. After construction: ``start_us``, ``formats`` {name:
    [(type, array size or 0, field)]}, ``info`` {key: value}, ``params``
    {name: value} (the initial parameters). ``scan`` streams the data section."""

    def __init__(self, path: str):
        self.path = str(path)
        if not Path(path).is_file():
            raise InputError("no such file", self.path)
        self.formats: dict[str, list] = {}
        self.info: dict = {}
        self.params: dict = {}
        self.appended = False
        with open(path, "rb") as fh:
            head = fh.read(16)
            if len(head) < 16 or head[:7] != MAGIC:
                raise InputError("not a ULog file (no ULog header)", self.path)
            self.version = head[7]
            self.start_us = struct.unpack_from("<Q", head, 8)[0]
            self.data_start = self._definitions(fh)

    def _definitions(self, fh) -> int:
        pos = 16
        while True:
            hdr = fh.read(3)
            if len(hdr) < 3:
                return pos
            size, typ = struct.unpack("<HB", hdr)
            if typ in b"ALC":
                return pos
            payload = fh.read(size)
            if len(payload) < size:
                return pos
            if typ == ord("F"):
                self._format(payload)
            elif typ == ord("I"):
                t, name, raw = _kv(payload)
                self.info[name] = _value(t, raw)
            elif typ == ord("P"):
                t, name, raw = _kv(payload)
                self.params[name] = _value(t, raw)
            elif typ == ord("B") and len(payload) >= 40:
                incompat = payload[8:16]
                if incompat[0] & ~1 or any(incompat[1:]):
                    raise InputError("the ULog file sets an incompatible flag this reader does "
                                     "not know", self.path)
                self.appended = bool(incompat[0] & 1)
            elif typ not in KNOWN:
                raise InputError(f"damaged ULog definitions section at byte {pos}", self.path)
            pos += 3 + size

    def _format(self, payload: bytes) -> None:
        text = payload.decode("utf-8", "replace")
        name, _, body = text.partition(":")
        fields = []
        for f in body.split(";"):
            f = f.strip()
            if not f:
                continue
            typ, _, fname = f.partition(" ")
            size = 0
            if typ.endswith("]") and "[" in typ:
                typ, n = typ[:-1].split("[")
                size = int(n)
            fields.append((typ, size, fname))
        self.formats[name] = fields

    def dtype(self, name: str) -> np.dtype:
        """The packed record dtype of a topic (pyulog's flattened names,
        trailing padding fields dropped)."""
        out: list[tuple[str, str]] = []

        def flat(prefix: str, tname: str, depth: int = 0):
            if tname not in self.formats or depth > 8:
                raise InputError(f"ULog format of {tname!r} missing", self.path)
            for typ, size, fname in self.formats[tname]:
                if typ in TYPES:
                    if size:
                        out.extend((f"{prefix}{fname}[{i}]", TYPES[typ]) for i in range(size))
                    else:
                        out.append((prefix + fname, TYPES[typ]))
                elif size:
                    for i in range(size):
                        flat(f"{prefix}{fname}[{i}].", typ, depth + 1)
                else:
                    flat(f"{prefix}{fname}.", typ, depth + 1)

        flat("", name)
        while out and out[-1][0].split(".")[-1].startswith("_padding"):
            out.pop()
        # padding fields inside keep their bytes under unique names
        seen: dict[str, int] = {}
        uniq = []
        for k, t in out:
            if k in seen:
                seen[k] += 1
                k = f"{k}#{seen[k]}"
            else:
                seen[k] = 0
            uniq.append((k, t))
        return np.dtype(uniq)

    def scan(self, topics, once=(), block: int = BLOCK) -> Iterator[list]:
        """Yield, block by block, [(topic, multi_id, records)] of the wanted
        ``topics`` (names); ``once``: topics of which only the first block's
        records are wanted (a device id). Meanwhile: ``subscriptions`` {(topic,
        multi_id)}, ``param_changes`` [(name, value)], ``dropouts`` (count,
        total ms), ``truncated_bytes``, ``corrupt_bytes``."""
        topics = set(topics) | set(once)
        self.subscriptions: set = set()
        self.param_changes: list = []
        self.dropouts = [0, 0]
        self.truncated_bytes = 0
        self.corrupt_bytes = 0
        wanted: dict[int, tuple] = {}  # msg_id -> (offsets, size, dtype, name, multi_id)
        dtypes: dict[str, np.dtype] = {}
        done_once: set = set()
        # one buffer for the whole file: a block read after the carried-over tail of
        # the last one (reading into fresh bytes objects fragments the heap)
        buf = bytearray(block + MAX_MSG)
        view = memoryview(buf)
        with open(self.path, "rb") as fh:
            fh.seek(self.data_start)
            carry = 0
            eof = False
            while not eof:
                got = fh.readinto(view[carry:carry + block])
                eof = not got
                n = carry + got
                pos = self._walk(buf, n, wanted, dtypes, topics, done_once)
                out = []
                win = _windows(buf, n)
                for mid, (offs, size, dt, name, multi) in list(wanted.items()):
                    if not offs:
                        continue
                    rec = win(offs, size).view(dt)[:, 0]
                    offs.clear()
                    out.append((name, multi, rec))
                    if name in once:
                        done_once.add((name, multi))
                        del wanted[mid]
                del win
                if out:
                    yield out
                if eof:
                    self.truncated_bytes = n - pos
                carry = n - pos
                buf[:carry] = buf[pos:n]

    def _walk(self, buf: bytes, n: int, wanted: dict, dtypes: dict, topics: set,
              done_once: set) -> int:
        """Note the offsets of wanted records in ``buf``; returns where the first
        incomplete message starts."""
        pos = 0
        unpack = struct.unpack_from
        while pos + 3 <= n:
            size = buf[pos] | (buf[pos + 1] << 8)
            typ = buf[pos + 2]
            end = pos + 3 + size
            if end > n:
                break
            if typ == 68:  # 'D': the hot path
                w = wanted.get(buf[pos + 3] | (buf[pos + 4] << 8))
                if w is not None and size - 2 >= w[1]:
                    w[0].append(pos + 5)
            elif typ == 65:  # 'A' subscription: uint8 multi_id, uint16 msg_id, name
                multi, mid = unpack("<BH", buf, pos + 3)
                name = buf[pos + 6:end].decode("utf-8", "replace")
                self.subscriptions.add((name, multi))
                if name in topics and (name, multi) not in done_once:
                    if name not in dtypes:
                        dtypes[name] = self.dtype(name)
                    dt = dtypes[name]
                    wanted[mid] = ([], dt.itemsize, dt, name, multi)
            elif typ == 82:  # 'R' unsubscribe
                wanted.pop(unpack("<H", buf, pos + 3)[0], None)
            elif typ == 80:  # 'P' parameter change
                t, name, raw = _kv(buf[pos + 3:end])
                self.param_changes.append((name, _value(t, raw)))
            elif typ == 79:  # 'O' dropout: uint16 ms
                self.dropouts[0] += 1
                self.dropouts[1] += unpack("<H", buf, pos + 3)[0]
            elif typ not in KNOWN:  # corruption: resume after the next sync message
                k = buf.find(SYNC, pos + 1, n)
                if k < 0:
                    self.corrupt_bytes += max(0, n - 7 - pos)
                    return max(pos, n - 7)
                self.corrupt_bytes += k + len(SYNC) - pos
                pos = k + len(SYNC)
                continue
            pos = end
        return pos


def open_ulog(path: str) -> ULogReader:
    try:
        return ULogReader(path)
    except InputError:
        raise
    except (OSError, ValueError, struct.error, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read the ULog file: {exc}", str(path)) from None
