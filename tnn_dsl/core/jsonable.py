"""Plain JSON from numpy results: arrays to lists, numpy scalars to Python numbers, non-finite floats to
``null``, paths to strings (``json.dumps(to_jsonable(x), allow_nan=False)`` always works)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Mapping

import numpy as np

__all__ = ["to_jsonable"]


def to_jsonable(obj: Any, *, inf_as_text: bool = False) -> Any:
    """Make numpy scalars/arrays, paths and objects with ``to_dict()`` JSON-serialisable. NaN becomes
    ``None``; ±inf becomes ``None`` too, or ``"inf"``/``"-inf"`` with ``inf_as_text`` (where a reader must
    tell an infinite standard error from a missing one)."""
    if isinstance(obj, Mapping):
        return {str(k): to_jsonable(v, inf_as_text=inf_as_text) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v, inf_as_text=inf_as_text) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist(), inf_as_text=inf_as_text)
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (np.floating, float)):
        v = float(obj)
        if math.isfinite(v):
            return v
        return ("inf" if v > 0 else "-inf") if inf_as_text and math.isinf(v) else None
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, Path):
        return str(obj)
    if hasattr(obj, "to_dict"):
        return to_jsonable(obj.to_dict(), inf_as_text=inf_as_text)
    return obj
