"""Adding a catalogue effect is one class in model/effects.py style and nothing
else (issue 17): a toy effect defined here becomes available to simulate, emulate,
diagnose, apply and the displays with no edit outside its class."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pytest

from calib_cli.model.effects import ADDITIVE, CATALOGUE, Effect, ParamSpec, register_effect


@pytest.fixture
def toy():
    @register_effect
    @dataclass(frozen=True)
    class ToyHum(Effect):
        """A toy: an offset that takes the sign of each channel's input."""

        name: str = field(default="toy_hum", init=False)
        stage: int = field(default=ADDITIVE, init=False)
        description = "toy hum: an offset with the sign of the input"

        def specs(self, layout):
            acc = self.sensor == "accel"
            return [ParamSpec(self._key("toy_hum"), (layout.n,), "m/s^2" if acc else "rad/s",
                              1e-3, display=(1e3, "mm/s^2") if acc else (1e3, "mrad/s"))]

        def apply(self, p, ctx):
            ctx.y = ctx.y + p[self._key("toy_hum")] * np.sign(ctx.u)

    yield ToyHum
    CATALOGUE.pop("toy_hum")


HUM = [0.02, -0.01, 0.015]
PLAN = ("name = 'toy'\nkind = 'static'\nsample_rate_hz = 50.0\ntransition_s = 1.0\n"
        "[site]\nlatitude_deg = 45.0\n" + "".join(
            f"[[segment]]\nlabel = 'p{i}'\nattitude_deg = {a}\nduration_s = 2.0\n"
            for i, a in enumerate([[0, -90, 0], [0, 90, 0], [90, 0, 0], [-90, 0, 0], [0, 0, 0],
                                   [180, 0, 0], [45, 45, 0], [-45, 45, 30]])))


def _truths():
    from calib_cli.model.effects import Layout
    from calib_cli.model.truth import truth_from_dict

    base = {"params": {"accel_bias": [0.01, 0.0, -0.02]},
            "noise": {"accel_white": 0.0, "gyro_white": 0.0}}
    with_toy = {**base, "params": {**base["params"], "accel_toy_hum": HUM}}
    return truth_from_dict(base, Layout()), truth_from_dict(with_toy, Layout())


def test_toy_effect_simulates_and_emulates(toy):
    from calib_cli.acquire.emulator import Emulator
    from calib_cli.acquire.profile import load_imu_profile
    from calib_cli.io.plan import parse_plan
    from calib_cli.sim.simulate import simulate

    plan = parse_plan(PLAN, "<toy>")
    plain, hum = _truths()
    a, b = simulate(plan, plain, seed=1), simulate(plan, hum, seed=1)
    st = b.static_segments()[0]  # x up: +g on x, ~0 on y, z
    d = (b.accel - a.accel)[st.slice].mean(0)
    assert d[0] == pytest.approx(HUM[0] * np.sign(b.accel[st.slice, 0].mean()), abs=1e-9)
    emu = Emulator(load_imu_profile("generic-bin6"), truth=hum, site=plan.site, rate=50.0)
    emu0 = Emulator(load_imu_profile("generic-bin6"), truth=plain, site=plan.site, rate=50.0)
    try:
        y, y0 = emu.samples(0, 100)["accel"], emu0.samples(0, 100)["accel"]
    finally:
        emu.stop()
        emu0.stop()
    # level unit: the input is +g on z and 0 on x and y (sign 0: no hum there)
    np.testing.assert_allclose((y - y0).mean(0), [0.0, 0.0, HUM[2]], atol=1e-9)


def test_toy_effect_applies_displays_and_is_diagnosed(toy):
    from calib_cli.data import CalibrationResult
    from calib_cli.io.plan import parse_plan
    from calib_cli.methods.apply import apply_triad
    from calib_cli.methods.diagnose_candidates import candidates
    from calib_cli.methods.diagnose_problem import build_problem
    from calib_cli.model.display import display_of
    from calib_cli.model.truth import describe_effect
    from calib_cli.sim.simulate import simulate

    _, hum = _truths()
    rec = simulate(parse_plan(PLAN, "<toy>"), hum, seed=2)
    # apply: a calibration holding the toy effect is inverted by the numerical inverse
    cal = CalibrationResult("toy", dict(hum.params), {k: np.zeros_like(v) for k, v in
                                                       hum.params.items()},
                            {k: "m/s^2" for k in hum.params}, np.zeros((0, 0)), [], {},
                            model=[describe_effect(e) for e in hum.model.effects])
    f, _ = apply_triad(cal, rec.accel, rec.gyro)
    st = rec.static_segments()
    g = [np.linalg.norm(f[s.slice].mean(0)) for s in st]
    assert np.allclose(g, rec.site.gravity, atol=1e-6)
    # display units from its ParamSpec
    assert display_of("accel_toy_hum", "m/s^2") == (1e3, "mm/s^2")
    # diagnose: a candidate on every sensor, described in its own words
    with np.errstate(invalid="ignore", divide="ignore"):  # a noise-free record
        pb = build_problem(rec, "accel")
    cands, why = candidates(pb, None, "full", set())
    toys = [c for c in cands if c.name == "toy_hum"]
    assert toys and "toy_hum" not in why
    text = toys[0].effect.describe({"accel_toy_hum": np.array(HUM)},
                                   {"accel_toy_hum": np.full(3, 1e-3)})
    assert text.startswith("toy hum") and "mm/s^2" in text
