"""spctool.jsonsafe: JSON values of results (NaN → null), checked against json's own strict encoder."""

import json
import math

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from spctool.jsonsafe import json_safe

_leaf = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(2**62), 2**62),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=5),
)
_tree = st.recursive(
    _leaf,
    lambda kids: st.one_of(
        st.lists(kids, max_size=4), st.dictionaries(st.text(max_size=4), kids, max_size=4)
    ),
    max_leaves=20,
)


@given(_tree)
def test_every_tree_encodes_strictly_and_keeps_every_finite_value(tree):
    out = json_safe(tree)
    text = json.dumps(out, allow_nan=False)  # raises on NaN/inf: none may be left

    def same(a, b):  # b = a after the round trip: finite values kept, non-finite ones null
        if isinstance(a, float) and not math.isfinite(a):
            return b is None
        if isinstance(a, dict):
            return a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)
        if isinstance(a, (list, tuple)):
            return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b))
        return a == b and type(a) is type(b)

    assert same(tree, json.loads(text))


def test_numpy_values_become_python_values():
    doc = {1: np.float64(np.nan), "a": np.arange(3), "b": (np.int32(4), np.bool_(True), np.float32(0.5))}
    out = json_safe(doc)
    assert out == {"1": None, "a": [0, 1, 2], "b": [4, True, 0.5]}
    assert type(out["b"][0]) is int and type(out["b"][1]) is bool and type(out["b"][2]) is float
    assert json_safe(np.array([1.0, np.inf])) == [1.0, None]
