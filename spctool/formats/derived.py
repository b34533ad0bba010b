"""A small on-disk cache of values derived from data and costly to compute (the shape's largest diameter,
the vertex rows parsed from an ICQ file's text).

A value is stored under a digest of the exact bytes it is computed from (with their dtype and shape)
and the name and version of the computation, so it can never be served for other data or by another
algorithm: a changed file has another digest, and the old entry is simply not asked for again.  One
small JSON file per value (:func:`cached`), or one ``.npy`` file per float64 array
(:func:`lookup_array`, :func:`store_array`), written atomically, under ``$SPCTOOL_CACHE_DIR``, else
``$XDG_CACHE_HOME/spctool``, else ``~/.cache/spctool`` (``derived/``).  Reading never fails: a missing,
unreadable, corrupt or misshapen entry is a miss (the value is recomputed), and a cache that cannot be
written is skipped.  ``SPCTOOL_CACHE_DIR=`` (empty) turns the cache off.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import numpy as np

__all__ = ["cache_dir", "digest", "lookup", "store", "cached", "lookup_array", "store_array"]


def cache_dir() -> Path | None:
    """The folder of the entries (not created here), or None when the cache is off."""
    env = os.environ.get("SPCTOOL_CACHE_DIR")
    if env is not None:
        return Path(env) / "derived" if env.strip() else None
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "spctool" / "derived"


def digest(array) -> str:
    """Hex digest of an array's bytes, dtype and shape (C order)."""
    a = np.ascontiguousarray(array)
    h = hashlib.blake2b(digest_size=20)
    h.update(f"{a.dtype.str}{a.shape}".encode())
    h.update(memoryview(a).cast("B"))
    return h.hexdigest()


def _path(kind: str, key: str, suffix: str = ".json") -> Path | None:
    folder = cache_dir()
    return None if folder is None else folder / f"{kind}-{key}{suffix}"


def lookup(kind: str, key: str):
    """The value stored for (``kind``, ``key``), or None."""
    path = _path(kind, key)
    if path is None:
        return None
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(doc, dict) or doc.get("kind") != kind or doc.get("key") != key:
        return None
    return doc.get("value")


def store(kind: str, key: str, value) -> None:
    """Keep ``value`` (JSON-serialisable) for (``kind``, ``key``); silently skipped when not writable."""
    path = _path(kind, key)
    if path is None:
        return
    from spctool.formats import atomic

    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        text = json.dumps({"kind": kind, "key": key, "value": value})
        atomic.write_bytes(path, text.encode("utf-8"))
    except Exception:  # a read-only home, a full disk: the value is simply recomputed next time
        pass


def cached(kind: str, array, compute):
    """``compute()``, or the value kept for ``kind`` and ``array``'s bytes (then not computed)."""
    key = digest(array)
    value = lookup(kind, key)
    if value is None:
        value = compute()
        store(kind, key, value)
    return value


def lookup_array(kind: str, key: str, shape: tuple) -> np.ndarray | None:
    """The float64 array of ``shape`` stored for (``kind``, ``key``), or None (missing, unreadable, or
    of another shape or dtype)."""
    path = _path(kind, key, ".npy")
    if path is None:
        return None
    try:
        with open(path, "rb") as f:
            array = np.lib.format.read_array(f, allow_pickle=False)
    except (OSError, ValueError, EOFError):
        return None
    if array.dtype != np.float64 or array.shape != tuple(shape):
        return None
    return array


def store_array(kind: str, key: str, array) -> None:
    """Keep a float64 ``array`` for (``kind``, ``key``) as ``.npy``; silently skipped when not writable."""
    path = _path(kind, key, ".npy")
    if path is None:
        return
    import io

    from spctool.formats import atomic

    try:
        buf = io.BytesIO()
        np.lib.format.write_array(buf, np.ascontiguousarray(array, dtype=np.float64), allow_pickle=False)
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic.write_bytes(path, buf.getvalue())
    except Exception:  # a read-only home, a full disk: the value is simply recomputed next time
        pass
