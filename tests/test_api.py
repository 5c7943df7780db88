"""calib_cli.api: the documented example of docs/api.md runs as written, and the
names of __all__ exist."""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def test_all_names_exist():
    from calib_cli import api

    for name in api.__all__:
        assert hasattr(api, name), name


def test_docs_example_fits_and_applies(tmp_path, capsys):
    text = (REPO / "docs" / "api.md").read_text()
    code = re.search(r"```python\n(.*?)```", text, re.S).group(1)
    code = code.replace('"sample_data/', f'"{REPO}/sample_data/')
    cwd = os.getcwd()
    os.chdir(tmp_path)
    try:
        exec(compile(code, "docs/api.md", "exec"), {})
    finally:
        os.chdir(cwd)
    out = capsys.readouterr().out
    g_after, g_site = (float(x) for x in re.search(r"after correction: ([\d.]+) m/s\^2 "
                                                    r"\(site: ([\d.]+)\)", out).groups())
    assert abs(g_after - g_site) < 0.01
    from calib_cli.io.h5 import read_raw

    corr = read_raw(tmp_path / "corrected.h5", kinds=("corrected",))
    assert np.all(np.isfinite(corr.accel))
