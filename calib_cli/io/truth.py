"""Truth files (TOML, docs/simulate.md): read, check keys, convert to a ``Truth``."""

from __future__ import annotations

import tomllib
from pathlib import Path

from calib_cli.errors import InputError
from calib_cli.model.effects import Layout
from calib_cli.model.truth import Truth, truth_from_dict


def load_truth(path, layout: Layout) -> Truth:
    p = str(path)
    try:
        raw = tomllib.loads(Path(p).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError("no such file", p) from None
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise InputError(f"cannot read truth file: {exc}", p) from None
    except RecursionError:
        raise InputError("cannot read truth file: nested too deeply", p) from None
    from calib_cli.io.schema import check_truth_keys  # issue 15: typos are exit 3

    check_truth_keys(raw, p)
    return truth_from_dict(raw, layout, p)
