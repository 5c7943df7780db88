"""Compatibility re-exports: the truth model and effect serialisation live in
``model/truth.py``, reading a truth file in ``io/truth.py``. New code imports
from there (this module goes once the open branches are merged)."""

from calib_cli.io.truth import load_truth  # noqa: F401
from calib_cli.model.truth import (  # noqa: F401
    DEFAULT_NOISE,
    Truth,
    _key_owner,
    default_truth,
    describe_effect,
    effect_from_description,
    truth_from_dict,
)
