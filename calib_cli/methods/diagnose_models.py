"""The built-in methods' diagnose base models (CONTRACT.md section 5): each the method's
own fit model in the effect catalogue's terms, named by its ``Diagnose`` description in
the method table (methods/registry.py), which ``calib diagnose`` and ``calib fit
--with`` read; the engine (methods/diagnose.py, methods/fit_with.py) holds no list of
methods. A base model is ``base(pb, base) -> (effects, names, mount)``: the catalogue
effects, their names for the JSON, and whether the unit's mount angles are a nuisance
(methods/diagnose_fit.py); ``base`` is "full" or "diagonal" (diagonal scale factors:
the misalignment becomes a candidate)."""

from __future__ import annotations

import numpy as np

from calib_cli.errors import EstimationError
from calib_cli.model.effects import make_effect
from calib_cli.model.frames import attitude_to_rotation


def accel_base(pb, base: str = "full") -> tuple[list, list, bool]:
    """accel: bias and K (lower triangular where the attitudes are unknown)."""
    st = "diagonal" if base == "diagonal" else ("lower" if pb.scalar else "full")
    effects = [make_effect("bias", "accel"),
               make_effect("scale_misalignment", "accel", structure=st)]
    names = ["accel_bias", f"accel_K ({st})"]
    if pb.scalar:
        names.append("gravity direction of each position (nuisance: attitudes unknown)")
    return effects, names, False


def align_base(pb, base: str = "full") -> tuple[list, list, bool]:
    """align: biases and attitude (the positions' common attitude)."""
    effects = [make_effect("bias", "accel"), make_effect("bias", "gyro")]
    names = ["accel_bias", "gyro_bias",
             "attitude (from the two-position alignment; 3 angles refitted)"]
    return effects, names, True


def rimu_base(pb, base: str = "full") -> tuple[list, list, bool]:
    """rimu: b, ks, dEl, dAz per sensor (a common rotation is in them)."""
    effects, names = [], []
    for s in pb.sensors:
        effects += [make_effect("bias", s), make_effect("installation", s)]
        names += [f"{s}_bias", f"{s}_scale_error", f"{s}_dEl", f"{s}_dAz"]
    return effects, names, False


def turntable_base(pb, base: str = "full") -> tuple[list, list, bool]:
    """turntable: lower-triangular accel K, the unit's mount angles as nuisance."""
    st = "diagonal" if base == "diagonal" else "lower"
    gst = "diagonal" if base == "diagonal" else "full"
    effects = [make_effect("bias", "accel"),
               make_effect("scale_misalignment", "accel", structure=st),
               make_effect("bias", "gyro"),
               make_effect("scale_misalignment", "gyro", structure=gst)]
    names = ["accel_bias", f"accel_K ({st})", "gyro_bias", f"gyro_K ({gst})",
             "mount angles (nuisance)"]
    return effects, names, True


def align_positions(rec) -> tuple:
    """An align recording with the attitude of every static position from the
    two-position alignment (calib fit align), and the Problem's ``start`` (the biases)
    and ``seg_rot`` (each used position's body-to-ENU matrix): the base model then
    refits the biases and a common attitude correction (the mount nuisance)."""
    from dataclasses import replace

    from calib_cli.methods.align import fit_align

    # the plan's stated turns where it has them: an attitude integrated through the turn
    # would carry the gyro errors under diagnosis (a scale drift over a 130 deg turn)
    stated = any(s.kind == "turn" and s.rotation_angle is not None for s in rec.segments)
    res = fit_align(rec, rotation="plan" if stated else "auto")
    atts = res.stats.get("attitudes_all") or []
    statics = [i for i, s in enumerate(rec.segments) if s.kind == "static"]
    if len(atts) != len(statics):
        raise EstimationError(f"the alignment used {len(atts)} of the {len(statics)} static "
                              "positions; diagnose --method align needs all of them")
    segs = list(rec.segments)
    for i, a in zip(statics, atts):
        segs[i] = replace(segs[i], attitude=np.asarray(a, float))
    rec = rec.with_(segments=tuple(segs))
    start = {k: np.asarray(res.params[k], float) for k in ("accel_bias", "gyro_bias")}
    seg_rot = {i: attitude_to_rotation(s.attitude).as_matrix()
               for i, s in enumerate(rec.segments)
               if s.kind == "static" and s.attitude is not None}
    return rec, {"start": start, "seg_rot": seg_rot}
