"""spctool — surface-feature optical navigation the SPC way.

Layers (lower never import upper): ``formats`` (SPC files <-> dataclasses) ->
``geometry`` (camera, frames, shapes, height fields) -> ``photometry`` ->
``stages`` (pure functions) -> ``sim`` -> ``batch`` -> ``cli``.
"""

__version__ = "0.1.0"
