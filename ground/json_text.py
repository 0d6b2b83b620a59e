"""Strict JSON for everything the ground tool prints or logs: NaN and infinities become null
(bare NaN is not JSON), numpy scalars and arrays become numbers and lists."""

from __future__ import annotations

import json
import math
import sys


def plain(obj):
    """``obj`` with numpy values as Python ones and non-finite floats as None (recursively)."""
    if isinstance(obj, dict):
        return {k: plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [plain(v) for v in obj]
    np = sys.modules.get("numpy")  # not imported here: no numpy value can exist before numpy is loaded
    if np is not None and isinstance(obj, np.ndarray):
        return plain(obj.tolist())
    if np is not None and isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def dumps(obj, **kw) -> str:
    """``json.dumps`` of :func:`plain` ``(obj)``; refuses (ValueError) anything non-finite left over."""
    return json.dumps(plain(obj), allow_nan=False, **kw)
