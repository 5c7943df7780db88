"""Table rate profiles for simulation: the motion a table controller runs.

A profile is a list of polynomial pieces of the rate in time, so that the
angle (its integral) and the angular acceleration (its derivative) are exact
at any sample instant, whatever the sample rate. Families (plan keys of a
rotating segment, docs/simulate.md):

- ``rate_profile = [[t_s, rate_dps], ...]`` knots, joined according to
  ``rate_shape``:
  - ``"linear"`` (default): constant-acceleration ramps; the angular
    acceleration jumps at every ramp corner (trapezoidal profile, the way most
    table controllers move);
  - ``"smooth"``: smoothstep ramps (continuous angular acceleration);
  - ``"scurve"``: ramps with a trapezoidal acceleration of finite jerk
    ``rate_jerk_dps3`` (deg/s^3, default 1000); the acceleration is
    continuous, the jerk jumps;
- ``rate_oscillation = [amplitude_dps, frequency_hz]``: sinusoidal
  oscillation ``A sin(2 pi f t)`` for ``duration_s``;
- ``table_rate_dps``: a constant rate.

Rate wobble (a rough table's speed control) is added on top by the simulator
(``sim_table_wobble_dps``, ``sim_table_wobble_hz``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.polynomial import Polynomial

D2R = np.pi / 180.0


@dataclass(frozen=True)
class Piece:
    t0: float  # s, start of the piece
    t1: float  # s, end
    rate: Polynomial  # rad/s in the local time tau = t - t0


def _ramp_pieces(t0: float, t1: float, r0: float, r1: float, shape: str,
                 jerk: float) -> list[Piece]:
    T = t1 - t0
    dr = r1 - r0
    if dr == 0.0 or shape == "linear":
        return [Piece(t0, t1, Polynomial([r0, dr / T]))]
    if shape == "smooth":
        return [Piece(t0, t1, Polynomial([r0, 0.0, 3 * dr / T**2, -2 * dr / T**3]))]
    if shape != "scurve":
        raise ValueError(f"rate_shape must be linear, smooth or scurve, got {shape!r}")
    # trapezoidal acceleration: jerk phases of length tj at both ends, peak a
    disc = T**2 - 4 * abs(dr) / jerk
    tj = 0.5 * T if disc <= 0 else 0.5 * (T - np.sqrt(disc))
    a = dr / (T - tj)
    p1 = Polynomial([r0, 0.0, 0.5 * a / tj])
    r_a = r0 + 0.5 * a * tj
    pieces = [Piece(t0, t0 + tj, p1)]
    if T - 2 * tj > 1e-12:
        pieces.append(Piece(t0 + tj, t1 - tj, Polynomial([r_a, a])))
    r_b = r1 - 0.5 * a * tj
    pieces.append(Piece(t1 - tj, t1, Polynomial([r_b, a, -0.5 * a / tj])))
    return pieces


def knot_pieces(kt, kr, shape: str = "linear", jerk: float = 1000 * D2R) -> list[Piece]:
    """Pieces through the knots (times kt s, rates kr rad/s)."""
    out: list[Piece] = []
    for i in range(len(kt) - 1):
        out += _ramp_pieces(float(kt[i]), float(kt[i + 1]), float(kr[i]), float(kr[i + 1]),
                            shape, jerk)
    return out


def evaluate(pieces: list[Piece], t: np.ndarray):
    """Angle (rad, from 0 at the first piece's start), rate (rad/s) and angular
    acceleration (rad/s^2) at the times t (s, within the pieces)."""
    starts = np.array([p.t0 for p in pieces])
    k = np.clip(np.searchsorted(starts, t, side="right") - 1, 0, len(pieces) - 1)
    area = np.concatenate([[0.0], np.cumsum([p.rate.integ()(p.t1 - p.t0) for p in pieces])])
    theta = np.empty(len(t))
    rate = np.empty(len(t))
    accel = np.empty(len(t))
    for i in np.unique(k):
        m = k == i
        p = pieces[i]
        tau = t[m] - p.t0
        theta[m] = area[i] + p.rate.integ()(tau)
        rate[m] = p.rate(tau)
        accel[m] = p.rate.deriv()(tau)
    return theta, rate, accel


def oscillation(t: np.ndarray, amplitude: float, freq: float):
    """A sin(2 pi f t): angle, rate, angular acceleration at t (s, from the start)."""
    w = 2 * np.pi * freq
    return (amplitude / w * (1 - np.cos(w * t)), amplitude * np.sin(w * t),
            amplitude * w * np.cos(w * t))


def trapezoid_knots(duration_s: float, ramp_dps2: float, levels_dps, hold_s, rest_s: float = 3.0):
    """Knots of holds at the given levels joined by ramps of ``ramp_dps2``, starting and
    ending at rest; ``hold_s`` a number or a callable giving each hold's length."""
    knots = [[0.0, 0.0], [rest_s, 0.0]]
    t, r, k = rest_s, 0.0, 0
    while True:
        nr = float(levels_dps[k % len(levels_dps)])
        k += 1
        ramp = abs(nr - r) / ramp_dps2
        hold = hold_s() if callable(hold_s) else float(hold_s)
        if t + ramp + hold + abs(nr) / ramp_dps2 + rest_s > duration_s:
            break
        t += ramp
        knots.append([t, nr])
        t += hold
        knots.append([t, nr])
        r = nr
    t += abs(r) / ramp_dps2
    knots.append([t, 0.0])
    if duration_s > t:
        knots.append([duration_s, 0.0])
    return knots
