"""A streaming numpy reader of ArduPilot DataFlash ``.bin`` logs, memory flat
in the log's length (docs/import.md).

A log is a sequence of messages ``0xA3 0x95 type payload``; message type 128
(FMT: ``uint8 type, uint8 length, char[4] name, char[16] format, char[64]
columns``) defines every other type's fixed length and layout (format
characters as pymavlink's ``DFReader.FORMAT_TO_STRUCT``). Each block of the
file is parsed at once: numpy finds every ``0xA3 0x95`` pair, the FMT
definitions found among them are registered, and the chain of messages
(each one's length gives where the next starts) is followed through the
candidates with numpy, so a payload byte pair that happens to read
``0xA3 0x95`` is skipped and Python only runs once per break in the chain
(a false candidate or damage), not once per message. The records of each
wanted type are then gathered into one structured array (fixed-size records
of one type at a time). Damage is skipped as pymavlink skips it: from the
bad byte to the next header of a known type.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calib_cli.errors import InputError

HEAD1, HEAD2 = 0xA3, 0x95
FMT_TYPE = 128
FMT_LEN = 89
BLOCK = 2 << 20
# pymavlink DFReader.FORMAT_TO_STRUCT: numpy type and multiplier
FORMAT = {"a": ("<i2", 32, None), "b": ("i1", 1, None), "B": ("u1", 1, None),
          "g": ("<f2", 1, None), "h": ("<i2", 1, None), "H": ("<u2", 1, None),
          "i": ("<i4", 1, None), "I": ("<u4", 1, None), "f": ("<f4", 1, None),
          "n": ("S4", 1, None), "N": ("S16", 1, None), "Z": ("S64", 1, None),
          "c": ("<i2", 1, 0.01), "C": ("<u2", 1, 0.01), "e": ("<i4", 1, 0.01),
          "E": ("<u4", 1, 0.01), "L": ("<i4", 1, 1e-7), "d": ("<f8", 1, None),
          "M": ("i1", 1, None), "q": ("<i8", 1, None), "Q": ("<u8", 1, None)}


@dataclass(frozen=True)
class DFFormat:
    type: int
    name: str
    length: int  # whole message, header included
    columns: tuple[str, ...]
    dtype: np.dtype  # of the payload
    mults: dict  # column -> multiplier (pymavlink's scaled columns)

    def column(self, rec: np.ndarray, name: str) -> np.ndarray:
        v = rec[name]
        m = self.mults.get(name)
        return v * m if m is not None else v


def make_format(mtype: int, name: str, fmt: str, cols: str) -> DFFormat | None:
    """A DFFormat, or None when the definition is not self-consistent."""
    columns = tuple(c for c in cols.split(",") if c) if cols else ()
    if not fmt or len(columns) != len(fmt) or any(c not in FORMAT for c in fmt):
        return None
    fields, mults = [], {}
    for c, col in zip(fmt, columns):
        t, count, mult = FORMAT[c]
        fields.append((col, t) if count == 1 else (col, t, (count,)))
        if mult is not None:
            mults[col] = mult
    try:
        dt = np.dtype(fields)
    except (ValueError, TypeError):  # repeated column names
        return None
    return DFFormat(mtype, name, 3 + dt.itemsize, columns, dt, mults)


FMT_FORMAT = make_format(FMT_TYPE, "FMT", "BBnNZ", "Type,Length,Name,Format,Columns")


def _text(b: bytes) -> str:
    return b.split(b"\0", 1)[0].decode("ascii", "replace")


class DataFlashReader:
    """One DataFlash log: ``scan(names)`` streams the records of the named
    message types; ``formats`` {name: DFFormat} grows as FMT messages are read."""

    def __init__(self, path: str):
        self.path = str(path)
        if not Path(path).is_file():
            raise InputError("no such file", self.path)
        with open(path, "rb") as fh:
            head = fh.read(3)
        if len(head) < 3 or head[0] != HEAD1 or head[1] != HEAD2:
            raise InputError("not a DataFlash log (no 0xA3 0x95 message header at its start)",
                             self.path)
        self.by_type: dict[int, DFFormat] = {FMT_TYPE: FMT_FORMAT}
        self.formats: dict[str, DFFormat] = {"FMT": FMT_FORMAT}

    def _lengths(self) -> np.ndarray:
        lens = np.full(256, -1, dtype=np.int64)
        for t, f in self.by_type.items():
            lens[t] = f.length
        return lens

    def _register(self, arr: np.ndarray, cand: np.ndarray, n: int) -> None:
        """FMT definitions among the candidates (checked for consistency)."""
        for c in cand[arr[cand + 2] == FMT_TYPE].tolist():
            if c + FMT_LEN > n:
                continue
            rec = arr[c + 3:c + FMT_LEN].view(FMT_FORMAT.dtype)[0]
            f = make_format(int(rec["Type"]), _text(rec["Name"]), _text(rec["Format"]),
                            _text(rec["Columns"]))
            if f is None or f.length != int(rec["Length"]) or not f.name.isprintable():
                continue
            old = self.by_type.get(f.type)
            if old is None or old.dtype != f.dtype or old.name != f.name:
                if old is not None:
                    self.formats.pop(old.name, None)
                self.by_type[f.type] = f
                self.formats[f.name] = f

    def scan(self, names, block: int = BLOCK) -> Iterator[dict]:
        """Yield, block by block, {name: records} of the wanted message types
        (records: structured arrays of the payloads). Meanwhile
        ``skipped_bytes`` (damage) and, at the end, ``truncated_bytes``."""
        names = set(names)
        self.skipped_bytes = 0
        self.truncated_bytes = 0
        buf = bytearray(block + 1024)  # one buffer: each block after the carried tail
        view = memoryview(buf)
        with open(self.path, "rb") as fh:
            carry = 0
            eof = False
            while not eof:
                room = len(buf) - carry
                if room < block // 2:  # a tail of damage longer than a message: grow
                    buf = buf + bytearray(block)
                    view = memoryview(buf)
                    room = len(buf) - carry
                got = fh.readinto(view[carry:carry + min(block, room)])
                eof = not got
                n = carry + got
                arr = np.frombuffer(buf, np.uint8, n)
                pos, valid = self._walk(arr, n)
                out = {}
                if len(valid):
                    types = arr[valid + 2]
                    for name in names:
                        f = self.formats.get(name)
                        if f is None:
                            continue
                        sel = valid[types == f.type]
                        if len(sel):
                            win = np.lib.stride_tricks.sliding_window_view(arr, f.length - 3)
                            out[name] = win[sel + 3].view(f.dtype)[:, 0]
                            del win
                del arr
                if out:
                    yield out
                if eof:
                    self.truncated_bytes = n - pos
                carry = n - pos
                buf[:carry] = buf[pos:n]

    def _walk(self, arr: np.ndarray, n: int) -> tuple[int, np.ndarray]:
        """(where the first incomplete message starts, the start offsets of the
        whole messages in arr[:n])."""
        if n < 3:
            return 0, np.zeros(0, np.int64)
        cand = np.flatnonzero((arr[:n - 2] == HEAD1) & (arr[1:n - 1] == HEAD2))
        if not len(cand):
            self.skipped_bytes += max(0, n - 2)
            return max(0, n - 2), cand
        self._register(arr, cand, n)
        lens = self._lengths()
        L = lens[arr[cand + 2]]
        nxt = cand + L
        m = len(cand)
        ok = np.zeros(m, bool)
        ok[:-1] = (L[:-1] > 0) & (nxt[:-1] == cand[1:])
        bad = np.flatnonzero(~ok)  # the last candidate is always here
        runs = []
        i = 0
        if cand[0] != 0:
            self.skipped_bytes += int(cand[0])
        pos = n
        while True:
            k = int(bad[np.searchsorted(bad, i)])
            if L[k] > 0 and nxt[k] <= n:  # message k is whole: the chain goes on at nxt[k]
                runs.append((i, k + 1))
                p = int(nxt[k])
                j = int(np.searchsorted(cand, p))
                if j < m and cand[j] == p:
                    i = j
                    continue
                if j == m:  # the block ends here (or within the next header)
                    pos = p
                    break
                self.skipped_bytes += int(cand[j]) - p  # damage: resume at the next header
                i = j
                continue
            if i < k:
                runs.append((i, k))
            if L[k] > 0:  # message k runs past the block: it starts the next one
                pos = int(cand[k])
                break
            # no known type at k: a stray header pair; resume at the next candidate
            i = k + 1
            if i >= m:
                pos = max(int(cand[k]) + 1, n - 2)
                self.skipped_bytes += pos - int(cand[k])
                break
            self.skipped_bytes += int(cand[i] - cand[k])
        if not runs:
            return pos, np.zeros(0, np.int64)
        mark = np.zeros(m + 1, np.int64)
        for a, b in runs:
            mark[a] += 1
            mark[b] -= 1
        return pos, cand[np.cumsum(mark[:m]) > 0]


def open_dataflash(path: str) -> DataFlashReader:
    try:
        return DataFlashReader(path)
    except InputError:
        raise
    except (OSError, ValueError) as exc:
        raise InputError(f"cannot read the DataFlash log: {exc}", str(path)) from None
