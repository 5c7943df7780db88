"""Typed reading of a parsed TOML table (device profiles): a number is a number
(not a bool, not a string), finite and in range; a string is a string without
NUL; an unknown key is refused naming the closest known one. Every failure is
one InputError naming the file and the key (exit 3)."""

from __future__ import annotations

import math

from calib_cli.errors import InputError

_MISSING = object()


class Typed:
    """Checked getters over the tables of one file (``path``)."""

    def __init__(self, path: str):
        self.path = path

    def fail(self, msg: str):
        raise InputError(msg, self.path)

    def keys(self, table: dict, known, where: str = "") -> None:
        from calib_cli.io.schema import closest

        for key in table:
            if key not in known:
                near = closest(str(key), known)
                hint = f"; did you mean {near}?" if near else ""
                self.fail(f"{where}unknown key {key!r}{hint} (known: "
                          f"{', '.join(sorted(known))})")

    def num(self, table: dict, key: str, where: str = "", default=_MISSING, lo=None, hi=None,
            integer: bool = False, lo_open: bool = False):
        """A finite number in [lo, hi] (lo excluded with ``lo_open``); ``integer``:
        a TOML integer."""
        v = table.get(key, _MISSING) if isinstance(table, dict) else _MISSING
        name = f"{where}{key}"
        if v is _MISSING:
            if default is _MISSING:
                self.fail(f"{name} is missing")
            return default
        kind = "an integer" if integer else "a number"
        if isinstance(v, bool) or not isinstance(v, (int, float)) or \
                (integer and not isinstance(v, int)):
            self.fail(f"{name} must be {kind}, got {v!r}")
        if not math.isfinite(v):
            self.fail(f"{name} must be a finite number, got {v!r}")
        if lo is not None and (v < lo or (lo_open and v == lo)):
            self.fail(f"{name} must be {'>' if lo_open else '>='} {lo:g}, got {v!r}")
        if hi is not None and v > hi:
            self.fail(f"{name} must be <= {hi:g}, got {v!r}")
        return v

    def text(self, table: dict, key: str, where: str = "", default=_MISSING, choices=None,
             allow_empty: bool = True) -> str:
        v = table.get(key, _MISSING) if isinstance(table, dict) else _MISSING
        name = f"{where}{key}"
        if v is _MISSING:
            if default is _MISSING:
                self.fail(f"{name} is missing")
            return default
        if not isinstance(v, str):
            self.fail(f"{name} must be a string, got {v!r}")
        if "\x00" in v:
            self.fail(f"{name} must not contain a NUL character")
        if not allow_empty and not v:
            self.fail(f"{name} must not be empty")
        if choices is not None and v not in choices:
            self.fail(f"{name} must be one of {', '.join(map(str, choices))}, got {v!r}")
        return v

    def flag(self, table: dict, key: str, where: str = "", default: bool = False) -> bool:
        v = table.get(key, default) if isinstance(table, dict) else default
        if not isinstance(v, bool):
            self.fail(f"{where}{key} must be true or false, got {v!r}")
        return v

    def table(self, raw: dict, key: str, where: str = "", default=None) -> dict:
        v = raw.get(key, _MISSING)
        if v is _MISSING:
            return {} if default is None else default
        if not isinstance(v, dict):
            self.fail(f"{where}[{key}] must be a table")
        return v

    def tables(self, raw: dict, key: str, where: str = "", limit: int = 4096) -> list[dict]:
        v = raw.get(key, [])
        if not isinstance(v, list) or not all(isinstance(t, dict) for t in v):
            self.fail(f"{where}{key} must be a list of tables ([[{key}]])")
        if len(v) > limit:
            self.fail(f"{where}{key}: {len(v)} entries, at most {limit}")
        return v

    def hexbytes(self, table: dict, key: str, where: str = "", default=_MISSING) -> bytes:
        s = self.text(table, key, where, default=None if default is not _MISSING else _MISSING)
        if s is None:
            return default
        try:
            return bytes.fromhex(s)
        except ValueError:
            self.fail(f"{where}{key} must be hex bytes like \"AA 55\", got {s!r}")
