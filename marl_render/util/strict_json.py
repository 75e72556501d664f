"""JSON that every parser reads: no bare NaN or Infinity tokens.

Python's ``json`` writes a float NaN as the bare token ``NaN``, which is not JSON: JavaScript's
``JSON.parse`` and Python's own ``json.loads(..., parse_constant=...)`` reject it. What the
project writes goes through ``dumps`` / ``dump`` here, which write a non-finite float as ``null``
(a value that is not a number: a normalised score where random and the heuristic tie, a checkpoint
that held a NaN). Readers take ``null`` where a number may be undefined.

    text = dumps(rows, indent=1)        # NaN, inf -> null
    data = loads(text)                  # json.loads that refuses NaN / Infinity tokens
"""
from __future__ import annotations

import json
import math

import numpy as np


def finite_or_null(value):
    """`value` with every non-finite float (Python or numpy), in any dict, list or tuple, as None."""
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, dict):
        return {key: finite_or_null(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite_or_null(item) for item in value]
    return value


def dumps(value, **kwargs) -> str:
    """json.dumps of finite_or_null(value); never a bare NaN or Infinity token."""
    return json.dumps(finite_or_null(value), allow_nan=False, **kwargs)


def dump(value, file, **kwargs) -> None:
    """json.dump of finite_or_null(value) into the text file `file`."""
    json.dump(finite_or_null(value), file, allow_nan=False, **kwargs)


def _refuse(token: str):
    raise ValueError(f"not strict JSON: the bare token {token} (write null for a value that is not a number)")


def loads(text: str):
    """json.loads that refuses the NaN, Infinity and -Infinity tokens (ValueError naming the token)."""
    return json.loads(text, parse_constant=_refuse)
