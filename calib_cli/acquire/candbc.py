"""CAN messages of an IMU profile: laid out in the profile ([[message]] with
typed fields and byte offsets), or described by a DBC file read with cantools
(``dbc = "unit.dbc"`` beside the profile, and [[message]] entries naming the
DBC message and, per field, its ``signal``). cantools is an optional extra
(``pip install calib-cli[can-dbc]``)."""

from __future__ import annotations

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
