"""The cache of derived values (spctool.formats.derived): keyed by the data's bytes, never wrong, never
in the way (issue 42: the shape's largest diameter was recomputed by every command)."""

import numpy as np
import pytest

from spctool.formats import derived


def test_a_value_is_computed_once_per_data_and_never_served_for_other_data(monkeypatch, tmp_path):
    monkeypatch.setenv("SPCTOOL_CACHE_DIR", str(tmp_path))
    a = np.arange(12.0).reshape(4, 3)
    calls = []

    def compute(x):
        calls.append(1)
        return float(x.sum())

    assert derived.cached("sum-v1", a, lambda: compute(a)) == 66.0
    assert derived.cached("sum-v1", a.copy(), lambda: compute(a)) == 66.0 and len(calls) == 1
    b = a.copy()
    b[3, 2] = np.nextafter(b[3, 2], 99.0)  # one bit of one value: other data
    assert derived.digest(b) != derived.digest(a)
    assert derived.cached("sum-v1", b, lambda: compute(b)) == pytest.approx(66.0) and len(calls) == 2
    assert derived.digest(a.reshape(3, 4)) != derived.digest(a)  # same bytes, other shape
    # a corrupt or foreign entry is a miss, and is replaced
    path = tmp_path / "derived" / f"sum-v1-{derived.digest(a)}.json"
    path.write_text("{not json")
    assert derived.cached("sum-v1", a, lambda: compute(a)) == 66.0 and len(calls) == 3
    path.write_text('{"kind": "other", "key": "x", "value": 1}')
    assert derived.lookup("sum-v1", derived.digest(a)) is None


def test_an_unwritable_or_disabled_cache_only_recomputes(monkeypatch, tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("")
    monkeypatch.setenv("SPCTOOL_CACHE_DIR", str(blocker))  # derived/ cannot be made under a file
    assert derived.cached("sum-v1", np.ones(3), lambda: 3.0) == 3.0
    monkeypatch.setenv("SPCTOOL_CACHE_DIR", "")
    assert derived.cache_dir() is None and derived.cached("sum-v1", np.ones(3), lambda: 4.0) == 4.0


def test_the_shape_diameter_is_kept_and_equals_its_computation(monkeypatch, tmp_path):
    from spctool.formats.workdir import WorkDir
    from spctool.geometry import shape as shape_mod
    from spctool.sim.demo import demo_path

    monkeypatch.setenv("SPCTOOL_CACHE_DIR", str(tmp_path))
    icq = WorkDir(demo_path()).read_shape(None)
    computed = shape_mod._max_diameter(np.ascontiguousarray(shape_mod.PatchShape(icq)._verts))
    assert shape_mod.PatchShape(icq).max_diameter == computed  # computed, then kept
    assert len(list((tmp_path / "derived").glob("max-diameter-v1-*.json"))) == 1
    monkeypatch.setattr(shape_mod, "_max_diameter", lambda pts: pytest.fail("recomputed"))
    assert shape_mod.PatchShape(icq).max_diameter == computed  # read back, bit for bit


def test_the_numpy_diameter_parts_equal_the_kernels_bit_for_bit():
    """The diameter's numpy searches (no kernel to compile on a first run) return what the numba
    kernels return, to the last bit, ties and indices included."""
    from spctool.geometry import _raykernels as rk
    from spctool.geometry import shape as shape_mod

    rng = np.random.default_rng(5)
    for n in (2, 3, 40, 700):
        for points in (
            rng.normal(size=(n, 3)),
            np.round(rng.uniform(-1, 1, size=(n, 3))),  # many ties
            rng.normal(size=(n, 3)) * [3.0, 2.0, 0.5],
        ):
            p = np.ascontiguousarray(points)
            assert shape_mod.farthest_pair(p) == float(rk.farthest_pair(p))
            dirs = rng.normal(size=(64, 3))
            dirs = np.ascontiguousarray(dirs / np.linalg.norm(dirs, axis=1)[:, None])
            kernel = rk.directional_extremes(p, dirs, 16)
            for ours, theirs in zip(shape_mod.directional_extremes(p, dirs), kernel):
                assert np.array_equal(ours, theirs)


def test_an_array_is_kept_as_stored_and_a_misshapen_or_corrupt_entry_is_a_miss(monkeypatch, tmp_path):
    monkeypatch.setenv("SPCTOOL_CACHE_DIR", str(tmp_path))
    a = np.linspace(-1.0, 2.0, 7)
    key = derived.digest(a)
    assert derived.lookup_array("arr-v1", key, (7,)) is None
    derived.store_array("arr-v1", key, a)
    assert np.array_equal(derived.lookup_array("arr-v1", key, (7,)).view(np.int64), a.view(np.int64))
    assert derived.lookup_array("arr-v1", key, (8,)) is None  # another shape: not this entry
    path = tmp_path / "derived" / f"arr-v1-{key}.npy"
    path.write_bytes(path.read_bytes()[:-5])  # truncated
    assert derived.lookup_array("arr-v1", key, (7,)) is None
    path.write_bytes(b"not an npy file")
    assert derived.lookup_array("arr-v1", key, (7,)) is None
    monkeypatch.setenv("SPCTOOL_CACHE_DIR", "")
    derived.store_array("arr-v1", key, a)  # off: nothing written, nothing read
    assert derived.lookup_array("arr-v1", key, (7,)) is None


def test_an_icq_file_s_rows_are_read_once_per_exact_bytes(monkeypatch, tmp_path):
    """The demo's q = 64 shape (101,400 values) is parsed once; the same bytes again (another copy of the
    file too) come from the cache bit for bit, and a file differing in one digit is parsed anew."""
    from spctool.formats import icq
    from spctool.sim.demo import demo_path

    monkeypatch.setenv("SPCTOOL_CACHE_DIR", str(tmp_path / "cache"))
    data = (demo_path() / "SHAPEFILES" / "SHAPE.TXT").read_bytes()
    (tmp_path / "a.txt").write_bytes(data)
    first = icq.read_icq(tmp_path / "a.txt")
    assert len(list((tmp_path / "cache" / "derived").glob("icq-rows-v1-*.npy"))) == 1
    real_parse = icq._parse_rows
    monkeypatch.setattr(icq, "_parse_rows", lambda *a: pytest.fail("parsed again"))
    (tmp_path / "b.txt").write_bytes(data)
    again = icq.read_icq(tmp_path / "b.txt")
    assert np.array_equal(again.vertices.view(np.int64), first.vertices.view(np.int64))
    assert np.array_equal(again.albedo.view(np.int64), first.albedo.view(np.int64))
    assert icq.format_icq(again) == data.decode("latin-1")  # the text kept for writing is the file's
    # one digit changed in the last vertex line: other bytes, parsed again, that value differs
    changed = data.rstrip(b"\n")
    cut = changed.rfind(b"\n") + 1
    line = changed[cut:].decode()
    digit = len(line.rstrip()) - 1
    line2 = line[:digit] + ("1" if line[digit] != "1" else "2") + line[digit + 1 :]
    (tmp_path / "c.txt").write_bytes(changed[:cut] + line2.encode() + b"\n")
    parsed = []
    monkeypatch.setattr(icq, "_parse_rows", lambda *a: parsed.append(1) or real_parse(*a))
    other = icq.read_icq(tmp_path / "c.txt")
    assert parsed == [1]
    assert not np.array_equal(other.albedo, first.albedo)
    assert np.array_equal(other.vertices, first.vertices)  # the albedo column was the one changed
    # the parse itself equals a reading without any cache
    monkeypatch.setenv("SPCTOOL_CACHE_DIR", "")
    plain = icq.read_icq(tmp_path / "c.txt")
    assert np.array_equal(plain.albedo.view(np.int64), other.albedo.view(np.int64))
