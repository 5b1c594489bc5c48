"""Checks shared by the typed dataclass configs (``ReconConfig``, ``DeformationConfig``, ...): every field
holds the kind of value its default has, so that a config file's mistake is named when it is read."""

from __future__ import annotations

import math
import numbers
from dataclasses import MISSING, fields

from endogsim.errors import DataError

__all__ = ["check_typed_fields"]


def check_typed_fields(config: object, prefix: str = "") -> None:
    """Every field of the dataclass ``config`` holds the kind of value its declared default has (a number
    where a number goes, an integer where a count goes, true/false for a switch, text for a name), and
    numbers are finite: a config file's ``"iters": "100"`` is named here, not met deep in a run. Fields
    whose default is None or made by a factory (nested configs) are not checked here. A whole number
    written as a float (TOML's ``iters = 1e4``) is taken as the integer. ``prefix`` names a nested config
    in the messages ("deformation.")."""
    for f in fields(config):
        v, d = getattr(config, f.name), f.default
        if d is MISSING or d is None:
            continue
        if isinstance(d, bool):
            ok, kind = isinstance(v, bool), "true or false"
        elif isinstance(d, int):
            if isinstance(v, float) and v.is_integer():
                v = int(v)
                setattr(config, f.name, v)
            ok, kind = isinstance(v, numbers.Integral) and not isinstance(v, bool), "an integer"
        elif isinstance(d, float):
            ok = isinstance(v, numbers.Real) and not isinstance(v, bool) and math.isfinite(v)
            kind = "a finite number"
        elif isinstance(d, str):
            ok, kind = isinstance(v, str), "text"
        elif isinstance(d, tuple):
            ok = isinstance(v, (tuple, list)) and all(isinstance(x, numbers.Integral) and not isinstance(x, bool)
                                                      for x in v)
            kind = "a list of integers"
        else:
            continue
        if not ok:
            raise DataError(f"{prefix}{f.name} = {v!r} must be {kind}")
