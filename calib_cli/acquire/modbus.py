"""Modbus RTU framing (the serial Modbus that climatic-chamber controllers
speak): a frame is slave address, function code, data, then the CRC-16/MODBUS
of all of it, low byte first. Only what a chamber driver needs: read holding
(03) or input (04) registers, write a single register (06), and the
exception reply (function | 0x80, one code byte).

Written here (no Modbus library is a dependency); the CRC is the shared
table-driven one (acquire/checksum.py, "crc-16/modbus"), checked against
the Modbus specification's example frames in tests/test_chamber.py.
"""

from __future__ import annotations

from calib_cli.acquire.checksum import NAMED_CRCS, Crc

_w, _p, _i, _ri, _ro, _xo, _ = NAMED_CRCS["crc-16/modbus"]
CRC16 = Crc(_w, _p, _i, _ri, _ro, _xo)

READ_HOLDING, READ_INPUT, WRITE_SINGLE = 0x03, 0x04, 0x06
EXCEPTIONS = {1: "illegal function", 2: "illegal data address", 3: "illegal data value",
              4: "slave device failure", 5: "acknowledge", 6: "slave device busy"}


class ModbusError(Exception):
    """A malformed, mismatched or exception reply."""


def crc(data: bytes) -> bytes:
    """The two CRC bytes appended to a frame (low byte first)."""
    return CRC16.compute(bytes(data)).to_bytes(2, "little")


def frame(slave: int, function: int, data: bytes) -> bytes:
    body = bytes([slave & 0xFF, function & 0xFF]) + bytes(data)
    return body + crc(body)


def check(fr: bytes) -> bool:
    """True when the last two bytes are the CRC of the rest."""
    return len(fr) >= 4 and crc(fr[:-2]) == bytes(fr[-2:])


def read_request(slave: int, address: int, count: int = 1, function: int = READ_HOLDING) -> bytes:
    return frame(slave, function, address.to_bytes(2, "big") + count.to_bytes(2, "big"))


def write_request(slave: int, address: int, value: int) -> bytes:
    """Write one 16-bit register (function 06); ``value`` is taken modulo 2^16
    (a negative number is sent as its two's complement)."""
    return frame(slave, WRITE_SINGLE, address.to_bytes(2, "big")
                 + (int(value) & 0xFFFF).to_bytes(2, "big"))


def reply_length(function: int, count: int = 1) -> int:
    """Bytes of a normal reply: read -> addr fn n data(2 count) crc; write -> echo (8)."""
    return 5 + 2 * count if function in (READ_HOLDING, READ_INPUT) else 8


def parse_reply(fr: bytes, slave: int, function: int, count: int = 1) -> list[int]:
    """The register values of a read reply ([] for a write's echo). Raises
    ModbusError on a bad CRC, another slave or function, or an exception reply."""
    fr = bytes(fr)
    if len(fr) >= 5 and fr[1] == (function | 0x80) and check(fr[:5]):
        code = fr[2]
        raise ModbusError(f"exception {code} ({EXCEPTIONS.get(code, 'unknown')})")
    if len(fr) < reply_length(function, count):
        raise ModbusError(f"short reply ({len(fr)} bytes)")
    fr = fr[:reply_length(function, count)]
    if not check(fr):
        raise ModbusError("reply CRC mismatch")
    if fr[0] != slave or fr[1] != function:
        raise ModbusError(f"reply from slave {fr[0]} function {fr[1]}, expected {slave}/{function}")
    if function in (READ_HOLDING, READ_INPUT):
        if fr[2] != 2 * count:
            raise ModbusError(f"reply byte count {fr[2]}, expected {2 * count}")
        return [int.from_bytes(fr[3 + 2 * k:5 + 2 * k], "big") for k in range(count)]
    return []


def to_signed(v: int) -> int:
    return v - 0x10000 if v & 0x8000 else v
