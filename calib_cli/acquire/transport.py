"""Transports: a serial port (pyserial) that reconnects after a disconnect,
and a CAN bus (python-can)."""

from __future__ import annotations

import time

from calib_cli.errors import InputError


class TransportLost(Exception):
    """The device went away (unplugged, port closed)."""


class _Reconnecting:
    """``reconnect`` for a transport with ``open`` (raises InputError) and ``close``."""

    def reconnect(self, give_up_s: float, stop=None) -> bool:
        """Reopen the port until it comes back or ``give_up_s`` passes."""
        self.close()
        t_end = time.monotonic() + give_up_s
        while time.monotonic() < t_end and not (stop is not None and stop.is_set()):
            try:
                self.open()
                return True
            except InputError:
                time.sleep(0.1)
        return False


class SerialTransport(_Reconnecting):
    """Reads whatever arrived, in slices of ``read_timeout`` seconds."""

    def __init__(self, port: str, settings: dict | None = None, read_timeout: float = 0.02):
        self.port = port
        self.settings = settings or {}
        self.read_timeout = read_timeout
        self.ser = None

    def open(self) -> None:
        import serial

        s = self.settings
        try:
            self.ser = serial.Serial(self.port, baudrate=int(s.get("baudrate", 115200)),
                                     bytesize=int(s.get("bytesize", 8)),
                                     parity=str(s.get("parity", "N")),
                                     stopbits=float(s.get("stopbits", 1)),
                                     timeout=self.read_timeout)
        except (serial.SerialException, ValueError, OSError) as exc:
            raise InputError(f"cannot open serial port: {exc}", self.port) from None
        self.ser.reset_input_buffer()  # stale bytes from before the recording

    def read(self) -> bytes:
        import serial

        try:
            return self.ser.read(1 << 16)
        except (serial.SerialException, OSError, TypeError) as exc:
            raise TransportLost(str(exc)) from None

    def write(self, data: bytes) -> None:
        self.ser.write(data)

    def close(self) -> None:
        if self.ser is not None:
            try:
                self.ser.close()
            except Exception:  # noqa: BLE001 - a port that vanished may fail to close
                pass
            self.ser = None


class CanTransport(_Reconnecting):
    """Yields (arbitration_id, data) pairs from a python-can bus."""

    def __init__(self, interface: str, channel: str, bitrate: int | None = None,
                 read_timeout: float = 0.02):
        self.interface, self.channel, self.bitrate = interface, channel, bitrate
        self.read_timeout = read_timeout
        self.bus = None

    def open(self) -> None:
        import can

        kw = {}
        if self.bitrate and self.interface not in ("virtual",):
            kw["bitrate"] = int(self.bitrate)
        try:
            self.bus = can.Bus(interface=self.interface, channel=self.channel, **kw)
        except (can.CanError, OSError, ValueError, ImportError) as exc:
            raise InputError(f"cannot open CAN bus {self.interface}:{self.channel}: {exc}",
                             self.channel) from None

    def read_messages(self) -> list[tuple[int, bytes]]:
        import can

        try:
            m = self.bus.recv(self.read_timeout)
            out = []
            while m is not None:
                if not m.is_error_frame and not m.is_remote_frame:
                    out.append((m.arbitration_id, bytes(m.data)))
                if len(out) > 4096:
                    break
                m = self.bus.recv(0)
            return out
        except (can.CanError, OSError) as exc:
            raise TransportLost(str(exc)) from None

    def close(self) -> None:
        if self.bus is not None:
            self.bus.shutdown()
            self.bus = None
