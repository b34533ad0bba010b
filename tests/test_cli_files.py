"""info / validate / convert on real files and on corrupted inputs (foundation issue)."""

import json
import shutil

import numpy as np
import pytest

from spctool.formats.icq import read_icq
from spctool.formats.maplet import Maplet, write_map
from spctool.formats.mesh import read_obj
from spctool.formats.photo import Photo, read_photo, write_photo


def test_version_and_help(run_cli):
    r = run_cli("--version")
    assert r.exit_code == 0 and "spctool" in r.stdout
    for cmd in ("info", "validate", "convert", "project"):
        r = run_cli(cmd, "--help")
        assert r.exit_code == 0 and "Example" in r.stdout


def test_info_json_has_every_row(run_cli, real):
    r = run_cli("info", "--json", real / "hayabusa-itokawa/N2395699394.SUM", real / "rosetta-67p/FA0115.LMK")
    assert r.exit_code == 0, r.stderr
    doc = json.loads(r.stdout)
    sum_doc, lmk_doc = doc["files"]
    assert sum_doc["kind"] == "sum" and len(sum_doc["landmarks"]) == 14 and len(sum_doc["limb_fits"]) == 68
    assert sum_doc["limb_fits"][0].keys() >= {"name", "sample", "line", "value"}
    assert lmk_doc["kind"] == "lmk" and len(lmk_doc["pictures"]) == 3
    assert lmk_doc["pictures"][1]["line"] == pytest.approx(-481.78)


def test_info_human_summary(run_cli, real):
    r = run_cli("info", real / "rosetta-67p/W48230079013.SUM")
    assert r.exit_code == 0
    assert "FA0115" in r.stdout and "MMFL 135.68" in r.stdout


def test_validate_exit_codes(run_cli, real, tmp_path):
    ok = run_cli(
        "validate", *sorted((real / "rosetta-67p").glob("*.LMK")), real / "rosetta-67p/W48230079013.SUM"
    )
    assert ok.exit_code == 0, ok.stderr
    bad = tmp_path / "BAD.SUM"
    text = (real / "rosetta-67p/W48230079013.SUM").read_text().replace("0.1356800000D+03", "0.13568000x0D+03")
    bad.write_text(text)
    # a SUM whose frame is not orthonormal: a semantic problem, listed too
    skew = tmp_path / "SKEW.SUM"
    lines = (real / "rosetta-67p/W48230079013.SUM").read_text().splitlines(keepends=True)
    lines[5] = lines[5].replace("0.", "0.9", 1)
    skew.write_text("".join(lines))
    r = run_cli("validate", bad, skew, real / "rosetta-67p/FA0115.LMK")
    assert r.exit_code == 2
    assert f"{bad}:4:" in r.stderr
    assert "not orthonormal" in r.stderr
    assert "FA0115.LMK: valid" in r.stdout


def test_convert_bennu_obj_to_icq_and_back(run_cli, real, tmp_path):
    for name, q in (("g_12570mm_alt_obj_0000n00000_v014.obj", 32), ("Bennu49k.obj", 64)):
        icq = tmp_path / f"SHAPE{q}.TXT"
        r = run_cli("convert", "--icq-style", "exact", real / "bennu-shapes" / name, icq)
        assert r.exit_code == 0, r.stderr
        shape = read_icq(icq)
        assert shape.q == q
        back = tmp_path / f"back{q}.obj"
        assert run_cli("convert", icq, back).exit_code == 0
        np.testing.assert_array_equal(
            read_obj(back).vertices, read_obj(real / "bennu-shapes" / name).vertices
        )


def test_convert_same_format_is_byte_identical(run_cli, real, tmp_path):
    for src in (
        real / "rosetta-67p/W48230079013.SUM",
        real / "hayabusa-itokawa/N2395699394.SUM",
        real / "rosetta-67p/GD0036.LMK",
    ):
        dst = tmp_path / src.name
        assert run_cli("convert", src, dst).exit_code == 0
        assert dst.read_bytes() == src.read_bytes()


def test_convert_refuses_to_overwrite_and_keeps_backup(run_cli, real, tmp_path):
    src = tmp_path / "W.SUM"
    shutil.copy(real / "rosetta-67p/W48230079013.SUM", src)
    r = run_cli("convert", src, src)
    assert r.exit_code == 2 and "refusing to overwrite the input" in r.stderr
    r = run_cli("convert", "--force", "--backup", src, src)
    assert r.exit_code == 0
    assert (tmp_path / "W.SUM.bak").read_bytes() == src.read_bytes()


def _maplet():
    q = 3
    n = 2 * q + 1
    rng = np.random.default_rng(1)
    h = rng.normal(size=(n, n))
    alb = 1 + 0.1 * rng.normal(size=(n, n))
    valid = np.ones((n, n), bool)
    valid[0, 0] = False
    return Maplet.new(
        0.001, q, [0.1, 0.2, 0.3], [0, -1, 0], [1, 0, 0], [0, 0, 1], h, alb, valid, name="AB0001"
    )


def test_convert_map_to_images(run_cli, tmp_path):
    m = _maplet()
    src = tmp_path / "AB0001.MAP"
    write_map(src, m)
    r = run_cli("convert", src, tmp_path / "h.npz")
    assert r.exit_code == 0, r.stderr
    z = np.load(tmp_path / "h.npz")
    np.testing.assert_array_equal(z["heights"], m.heights)
    np.testing.assert_array_equal(z["valid"], m.valid)
    assert run_cli("convert", src, tmp_path / "h.fits").exit_code == 0
    from astropy.io import fits

    with fits.open(tmp_path / "h.fits") as hdul:
        np.testing.assert_allclose(hdul[0].data[m.valid], m.heights[m.valid])
        assert np.isnan(hdul[0].data[0, 0])
        assert hdul[0].header["SCALE"] == pytest.approx(0.001)
        np.testing.assert_allclose(hdul["ALBEDO"].data[m.valid], m.albedo[m.valid])
    assert run_cli("convert", src, tmp_path / "h.png").exit_code == 0
    img = read_photo(tmp_path / "h.png").data
    alb = read_photo(tmp_path / "h.albedo.png").data
    assert img.dtype == np.uint16 and img[0, 0] == 0 and img[m.valid].min() >= 1
    # monotone in height
    order = np.argsort(m.heights[m.valid])
    assert np.all(np.diff(img[m.valid][order].astype(int)) >= 0)
    np.testing.assert_array_equal(alb[m.valid], np.round(m.albedo[m.valid] * 100).astype(np.uint8))


def test_convert_photos_keep_16_bit_and_flip(run_cli, tmp_path):
    data = (np.arange(12 * 10, dtype=np.uint16).reshape(12, 10) * 500).astype(np.uint16)
    write_photo(tmp_path / "p.fits", Photo(data=data))
    assert run_cli("convert", tmp_path / "p.fits", tmp_path / "p.pgm").exit_code == 0
    np.testing.assert_array_equal(read_photo(tmp_path / "p.pgm").data, data)
    assert run_cli("convert", tmp_path / "p.pgm", tmp_path / "P.DAT").exit_code == 0
    r = run_cli("convert", "--npx", 10, "--nln", 12, tmp_path / "P.DAT", tmp_path / "q.png")
    assert r.exit_code == 0, r.stderr
    np.testing.assert_array_equal(read_photo(tmp_path / "q.png").data, data)
    assert run_cli("convert", "--flip-rows", tmp_path / "q.png", tmp_path / "f.png").exit_code == 0
    np.testing.assert_array_equal(read_photo(tmp_path / "f.png").data, data[::-1])
    r = run_cli("convert", tmp_path / "P.DAT", tmp_path / "r.png")
    assert r.exit_code == 2 and "needs its size" in r.stderr


CORRUPTIONS = {
    "truncated MAP": ("AB0001.MAP", lambda b: b[:-100], "byte"),
    "garbage SUM number": ("W.SUM", lambda b: b.replace(b"0.1356800000D+03", b"0.13x6800000D+03"), ":4:"),
    "missing END FILE": ("W.SUM", lambda b: b[: b.index(b"END FILE")], "END FILE"),
    "ICQ wrong vertex count": ("SHAPE.TXT", lambda b: b.rsplit(b"\n", 3)[0] + b"\n", "vert"),
}


@pytest.mark.parametrize("case", sorted(CORRUPTIONS))
def test_corrupted_inputs_exit_2_one_line(case, run_cli, real, tmp_path):
    name, corrupt, needle = CORRUPTIONS[case]
    if name == "AB0001.MAP":
        write_map(tmp_path / name, _maplet())
        raw = (tmp_path / name).read_bytes()
    elif name == "W.SUM":
        raw = (real / "rosetta-67p/W48230079013.SUM").read_bytes()
    else:
        run_cli("convert", real / "bennu-shapes/g_12570mm_alt_obj_0000n00000_v014.obj", tmp_path / "S.TXT")
        raw = (tmp_path / "S.TXT").read_bytes()
    p = tmp_path / name
    p.write_bytes(corrupt(raw))
    r = run_cli("info", p)
    assert r.exit_code == 2
    err = r.stderr.strip().splitlines()
    assert len(err) == 1, r.stderr
    assert err[0].startswith(f"spctool: error: {p}") and needle in err[0]
    assert "Traceback" not in r.stderr


def test_debug_shows_traceback(run_cli, tmp_path):
    p = tmp_path / "x.SUM"
    p.write_text("X\n")
    r = run_cli("--debug", "info", p)
    assert r.exit_code == 2 and "Traceback" in r.stderr


def test_usage_error_is_one_line(run_cli):
    r = run_cli("info")
    assert r.exit_code == 2
    assert len(r.stderr.strip().splitlines()) == 1 and r.stderr.startswith("spctool: error:")
