"""The files a fit reads besides its recording: calibrations given as options
(``calib fit gyro --accel CAL``, ``calib fit thermal --base CAL``, the same keys in a
batch step). Each is read once here, for the command line and the batch alike, and
handed to the method as a ``FileInput`` that says whether it was made from the very
recording being fitted (its input hashes, CONTRACT.md section 6): the method decides
what that means (the gyro fit propagates an independent accelerometer calibration's
uncertainty)."""

from __future__ import annotations

import json

from calib_cli.methods.method import FileInput
from calib_cli.methods.registry import get


def made_from(cal_path: str, raw_path: str | None) -> bool | None:
    """Whether the calibration file lists the recording file among its inputs
    (None without a recording path)."""
    from calib_cli.io.h5 import provenance, sha256_file

    if raw_path is None:
        return None
    try:
        used = json.loads(provenance(cal_path).get("input_sha256", "{}")).values()
    except (ValueError, AttributeError):
        used = ()
    return sha256_file(raw_path) in set(used)


def read_file_options(method: str, options: dict, raw_path: str | None = None) -> tuple[dict, list]:
    """The options with every calibration-file option read (a path -> FileInput), and
    the paths read (the fit's further inputs, for the output's provenance)."""
    from calib_cli.io.h5 import read_calibration

    m = get(method)
    out, paths = dict(options), []
    for name in m.file_option_names():
        v = out.get(name)
        if v is None or isinstance(v, FileInput) or not isinstance(v, (str, bytes)) and \
                not hasattr(v, "__fspath__"):
            continue
        p = str(v)
        out[name] = FileInput(read_calibration(p), p, made_from(p, raw_path))
        paths.append(p)
    return out, paths
