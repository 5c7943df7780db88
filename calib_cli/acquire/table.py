"""Turntable drivers: a serial table driven by its profile's command
templates and response patterns, and a manual "table" (the operator)."""

from __future__ import annotations

import time

import numpy as np
from scipy.spatial.transform import Rotation

from calib_cli.acquire.profile import TableProfile
from calib_cli.errors import InputError
from calib_cli.model.frames import attitude_to_rotation

R2D = 180.0 / np.pi


def describe_attitude(att_rad) -> str:
    """'+x up' for a position with a body axis up, else the angles in degrees."""
    up_body = attitude_to_rotation(att_rad).inv().apply([0.0, 0.0, 1.0])
    i = int(np.argmax(np.abs(up_body)))
    if abs(up_body[i]) > 0.999:
        return f"put {'+' if up_body[i] > 0 else '-'}{'xyz'[i]} up"
    r, p, y = np.asarray(att_rad) * R2D
    return f"set roll {r:.1f}, pitch {p:.1f}, yaw {y:.1f} deg"


class SerialTable:
    def __init__(self, prof: TableProfile, port: str, timeout: float = 1.0):
        import serial

        self.prof, self.port = prof, port
        t = prof.transport
        try:
            self.ser = serial.Serial(port, baudrate=int(t.get("baudrate", 115200)),
                                     timeout=timeout)
        except (serial.SerialException, ValueError, OSError) as exc:
            raise InputError(f"cannot open turntable port: {exc}", port) from None
        self.ser.reset_input_buffer()
        self.term = prof.terminator.encode()

    def _line(self) -> str:
        raw = self.ser.read_until(self.term[-1:])
        if not raw:
            raise InputError("the turntable did not answer", self.port)
        return raw.decode("ascii", "replace").strip()

    def _send(self, name: str, **kw) -> str:
        if name not in self.prof.commands:
            raise InputError(f"the table profile has no {name!r} command", self.prof.path)
        self.ser.write(self.prof.commands[name].format(**kw).encode() + self.term)
        return self._line()

    def _command(self, name: str, **kw) -> None:
        reply = self._send(name, **kw)
        ack = self.prof.responses.get("ack")
        if ack is not None and not ack.search(reply):
            raise InputError(f"the turntable refused {name!r}: {reply!r}", self.port)

    def move(self, att_rad, label: str = "") -> None:
        vals = {f"{a}_deg": float(v) * R2D
                for a, v in zip(("roll", "pitch", "yaw"), att_rad, strict=True)}
        self._command("move", **vals)

    def set_rate(self, rate_rad_s: float) -> None:
        self._command("rate", rate_dps=float(rate_rad_s) * R2D)

    def stop(self) -> None:
        if "stop" in self.prof.commands:
            self._command("stop")

    def status(self) -> str:
        reply = self._send("query_status")
        m = self.prof.responses["status"].search(reply)
        if m is None:
            raise InputError(f"unexpected status reply {reply!r}", self.port)
        return m.group("state")

    def settled(self) -> bool:
        return self.status() in self.prof.settled_states

    def angle(self):
        """Current [roll, pitch, yaw] (rad) where the table reports them."""
        if "query_angle" not in self.prof.commands or "angle" not in self.prof.responses:
            return None
        m = self.prof.responses["angle"].search(self._send("query_angle"))
        if m is None:
            return None
        d = m.groupdict()
        return np.array([float(d.get(f"{a}_deg") or 0.0) for a in ("roll", "pitch", "yaw")]) / R2D

    def close(self) -> None:
        self.ser.close()


class ManualTable:
    """The operator places the unit; ``ask`` shows a prompt and waits for Enter
    (it returns the line typed, e.g. "q" to end a repeat = "auto" segment)."""

    motorised = False

    def __init__(self, ask):
        self.ask = ask

    def move(self, att_rad, label: str = "") -> None:
        what = describe_attitude(att_rad) if att_rad is not None else "place the unit"
        self.ask(f"[{label}] {what}, hold it still, then press Enter")

    def turn(self, axis_body, angle_rad, label: str = "") -> None:
        ax = "xyz"[int(np.argmax(np.abs(axis_body)))]
        sign = "+" if axis_body[int(np.argmax(np.abs(axis_body)))] > 0 else "-"
        self.ask(f"[{label}] press Enter, then turn the unit {angle_rad * R2D:.0f} deg about "
                 f"{sign}{ax} and hold it still")

    def set_rate(self, rate_rad_s: float) -> None:
        raise InputError("a rotating segment needs a motorised table (--table PROFILE)")

    def stop(self) -> None:
        pass

    def settled(self) -> bool:
        return True

    def angle(self):
        return None

    def close(self) -> None:
        pass


def turn_target(att_rad, axis_body, angle_rad):
    """Attitude (rad) after turning by angle about a body axis."""
    from calib_cli.model.frames import rotation_to_attitude

    rot = attitude_to_rotation(att_rad) * Rotation.from_rotvec(np.asarray(axis_body) * angle_rad)
    return rotation_to_attitude(rot)


def wait(seconds: float) -> None:
    time.sleep(seconds)
