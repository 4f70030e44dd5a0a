"""Answers as JSON for scripts (``fmgs-client ... --json``): dataclasses, numpy arrays and scalars to plain
JSON values, one object per line."""

from __future__ import annotations

import dataclasses
import json
import math
import sys
from collections.abc import Mapping
from typing import IO, Any

import numpy as np


def jsonable(x: Any) -> Any:
    """Plain JSON values: dataclasses become objects (their fields), arrays nested lists, non-finite
    floats null (JSON has no NaN)."""
    if dataclasses.is_dataclass(x) and not isinstance(x, type):
        return {f.name: jsonable(getattr(x, f.name)) for f in dataclasses.fields(x)}
    if isinstance(x, np.ndarray):
        return jsonable(x.tolist())
    if isinstance(x, np.generic):
        return jsonable(x.item())
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, Mapping):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [jsonable(v) for v in x]
    if isinstance(x, bytes):
        return None  # PNG bytes stay out of JSON (the images are written to files)
    return x


def emit(obj: Any, out: IO[str] | None = None) -> None:
    """Write one JSON object on its own line."""
    stream = sys.stdout if out is None else out
    stream.write(json.dumps(jsonable(obj), allow_nan=False) + "\n")
    stream.flush()
