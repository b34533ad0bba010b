"""JSON values of spctool's results: NaN and ±inf become null, numpy scalars and arrays Python values.

JSON has no NaN (``json.dumps`` would write the invalid token ``NaN``), and a NaN in spctool's results
means "not measured": null says the same to every JSON reader (cli-contract.md "JSON output").
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["json_safe"]


def json_safe(x):
    """``x`` with every non-finite float → None, numpy scalars → Python scalars, arrays and tuples →
    lists and dict keys → str, recursively; other values unchanged."""
    if isinstance(x, dict):
        return {str(k): json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [json_safe(v) for v in x]
    if isinstance(x, np.ndarray):
        return json_safe(x.tolist())
    if isinstance(x, (np.floating, float)):
        return float(x) if math.isfinite(float(x)) else None
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x
