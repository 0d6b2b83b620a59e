"""Strict JSON for everything the ground tool prints or logs: NaN and infinities become null
(bare NaN is not JSON), numpy scalars and arrays become numbers and lists."""

from __future__ import annotations

import json
import math

import numpy as np


def plain(obj):
    """``obj`` with numpy values as Python ones and non-finite floats as None (recursively)."""
    if isinstance(obj, dict):
        return {k: plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return plain(obj.tolist())
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def dumps(obj, **kw) -> str:
    """``json.dumps`` of :func:`plain` ``(obj)``; refuses (ValueError) anything non-finite left over."""
    return json.dumps(plain(obj), allow_nan=False, **kw)
