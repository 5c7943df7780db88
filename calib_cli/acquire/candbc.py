"""CAN messages of an IMU profile: laid out in the profile ([[message]] with
typed fields and byte offsets), or described by a DBC file read with cantools
(``dbc = "unit.dbc"`` beside the profile, and [[message]] entries naming the
DBC message and, per field, its ``signal``). cantools is an optional extra
(``pip install calib-cli[can-dbc]``)."""

from __future__ import annotations

import dataclasses
import struct
from pathlib import Path

from calib_cli.errors import InputError

CAN_TYPES = {"u8": "B", "i8": "b", "u16": "H", "i16": "h", "u32": "I", "i32": "i",
             "u64": "Q", "i64": "q", "f32": "f", "f64": "d"}


def load_dbc(path: str):
    """A cantools Database from a DBC file, or InputError naming the file."""
    try:
        import cantools
    except ImportError:
        raise InputError("this profile describes its unit by a DBC file: install cantools "
                         "(pip install 'calib-cli[can-dbc]')", path) from None
    try:
        return cantools.database.load_file(path, database_format="dbc", strict=True)
    except FileNotFoundError:
        raise InputError("no such DBC file", path) from None
    except Exception as exc:  # noqa: BLE001 - cantools raises many parse errors
        raise InputError(f"cannot read the DBC file: {type(exc).__name__}: {exc}", path) \
            from None


def can_messages(t, raw: dict, path: str, byte_order: str):
    """(messages, dbc database or None) of a CAN profile."""
    from calib_cli.acquire.profile import (
        CHECKSUM_KEYS,
        FIELD_KEYS,
        IMU_KEYS,
        CanMessage,
        Checksum,
        _checksum,
        _field,
    )

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
    from calib_cli.acquire.profile import CanMessage, Checksum

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
