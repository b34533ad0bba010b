"""Tests of spctool.figures (and the commands that write figures): each figure is written, has the
expected size and is not blank, and where it encodes numbers — shift and residual vectors, the
correlation peak, bars — they sit where the numbers say (pixel colours at positions computed here
from the inputs or from the command's own table, independently of the drawing code)."""

from __future__ import annotations

import io
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image

from spctool import figures


def _near(px, xy, colour, r=1):
    """True when ``colour`` occurs within r pixels of canvas position ``xy``."""
    x, y = int(round(xy[0])), int(round(xy[1]))
    win = px[max(0, y - r) : y + r + 1, max(0, x - r) : x + r + 1].reshape(-1, 3)
    return any(tuple(int(v) for v in c) == tuple(colour) for c in win)


def _png(fig):
    data = fig.png()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 1000
    with Image.open(io.BytesIO(data)) as img:
        img.load()
        assert img.mode == "RGB" and img.size == fig.size
        px = np.asarray(img)
    assert px.std() > 5  # not blank
    return px


def _photo(nln=120, npx=160):
    ln, s = np.mgrid[0:nln, 0:npx]
    return 100.0 + 50.0 * np.sin(s / 9.0) * np.cos(ln / 13.0)


# ------------------------------------------------------------------------------------------------
# helpers


def test_colormap_ends_nan_and_monotone_luminance():
    c = figures.colormap(np.array([0.0, 0.5, 1.0, np.nan]), 0.0, 1.0)
    assert tuple(c[0]) == (68, 1, 84) and tuple(c[2]) == (253, 231, 37) and tuple(c[3]) == figures.GREY
    lum = figures.colormap(np.linspace(0, 1, 50), 0, 1) @ np.array([0.299, 0.587, 0.114])
    assert np.all(np.diff(lum) > -1e-9)


def test_nice_number_and_ticks():
    assert [figures.nice_number(x) for x in (0.7, 3.0, 9.9, 12.0, 49.0)] == [0.5, 2.0, 5.0, 10.0, 20.0]
    t = figures.ticks(0.0, 3.7)
    assert t[0] == 0.0 and t[-1] <= 3.7 and len(set(np.round(np.diff(t), 9))) == 1


@given(st.integers(1, 9), st.integers(1, 40), st.integers(1, 30))
@settings(max_examples=60, deadline=None)
def test_figure_xy_lands_in_the_enlarged_pixel(z, s, ln):
    # canvas position of SPC pixel (s, ln) is inside the z x z block that pixel becomes
    fig = figures.Figure(Image.new("RGB", (1, 1)), x0=3.0, y0=7.0, zoom=float(z))
    x, y = fig.xy(s, ln)
    assert 3 + (s - 1) * z <= x <= 3 + s * z - 1 and 7 + (ln - 1) * z <= y <= 7 + ln * z - 1
    assert x - (3 + (s - 1) * z) == pytest.approx((z - 1) / 2)  # the block's centre


def test_upscale_is_nearest_neighbour():
    a = np.arange(12, dtype=np.uint8).reshape(2, 2, 3)
    b = figures.upscale(a, 3)
    assert b.shape == (6, 6, 3) and np.array_equal(b[::3, ::3], a) and np.array_equal(b[2, 2], a[0, 0])


# ------------------------------------------------------------------------------------------------
# register overlay


def test_register_overlay_vectors_sit_at_magnified_shifts():
    photo = _photo()
    names = ["A", "B", "C", "D"]
    apriori = np.array([[30.0, 40.0], [100.0, 50.0], [60.0, 90.0], [130.0, 100.0]])
    measured = np.array([[31.5, 38.0], [97.0, 50.5], [np.nan, np.nan], [131.0, 101.0]])
    status = ["ok", "ok", "not-found", "low-correlation"]
    fig = figures.register_overlay(photo, (0, 255), names, apriori, measured, status, picture="P1", magnify=8)
    px = _png(fig)
    z = fig.zoom
    assert fig.size[0] == 160 * z and fig.size[1] > 120 * z and fig.magnify == 8
    for k in (0, 1, 3):
        # independent: canvas of SPC pixel p is (p - 1)·z + (z - 1)/2, plus the title band
        tip = (apriori[k] - 1 + 8 * (measured[k] - apriori[k])) * z + (z - 1) / 2 + np.array([0, fig.y0])
        assert np.allclose(fig.extra["tips"][k], tip)
        assert _near(px, tip, figures.status_colour(status[k]))
        mid = (apriori[k] - 1 + 4 * (measured[k] - apriori[k])) * z + (z - 1) / 2 + np.array([0, fig.y0])
        assert _near(px, mid, figures.status_colour(status[k]))
    # the failed landmark: an x in the not-found colour on its a-priori pixel, no vector
    a = fig.xy(*apriori[2])
    assert _near(px, (a[0] + 3, a[1] + 3), figures.STATUS_COLOURS["not-found"])
    assert np.isnan(fig.extra["tips"][2]).all()


def test_register_overlay_default_magnification_is_round_and_stated():
    apriori = np.array([[50.0, 50.0], [80.0, 60.0]])
    measured = apriori + [[0.3, 0.1], [0.2, -0.3]]
    fig = figures.register_overlay(_photo(), None, ["A", "B"], apriori, measured, ["ok", "ok"])
    mantissa = fig.magnify / 10 ** math.floor(math.log10(fig.magnify))
    assert mantissa in (1.0, 2.0, 5.0)
    med = np.median(np.hypot(*(measured - apriori).T))
    assert 15 <= fig.magnify * med <= 45


# ------------------------------------------------------------------------------------------------
# landmark panel


def _gaussian_surface(k=5, r0=6.3, c0=3.6):
    r, c = np.mgrid[0 : 2 * k + 1, 0 : 2 * k + 1]
    s = 0.9 * np.exp(-((r - r0) ** 2 + (c - c0) ** 2) / 6.0) - 0.1
    s[0, 0] = np.nan
    return s


def test_landmark_panel_peak_marker_and_surface_colours():
    s = _gaussian_surface()
    img = np.random.default_rng(1).uniform(1, 2, (49, 49))
    valid = np.ones_like(img, bool)
    valid[:5] = False
    fig = figures.landmark_panel(
        "LMK",
        "PIC",
        img,
        img * 0.9,
        s,
        left_valid=valid,
        peak_index=(6, 4),
        subpixel=(0.3, -0.4),
        spacing=2,
        rho=0.8,
        shift=(1.0, -2.0),
        status="ok",
    )
    px = _png(fig)
    assert fig.size[0] > 3 * 200 and fig.size[1] > 240
    ox, oy = fig.extra["surface_origin"]
    cell = fig.extra["cell"]
    # the red peak marker at the sub-pixel peak: column 4 - 0.4, row 6 + 0.3
    peak = (ox + (4 - 0.4) * cell, oy + (6 + 0.3) * cell)
    assert np.allclose(fig.extra["peak"], peak)
    assert _near(px, peak, figures.PEAK)
    # a surface cell away from the marker shows the colour map of its value; the NaN cell is grey
    vmin, vmax = fig.extra["range"]
    for r, c in ((1, 9), (9, 1), (10, 10)):
        got = px[int(oy + r * cell), int(ox + c * cell)]
        assert np.array_equal(got, figures.colormap(s[r, c], vmin, vmax))
    assert np.array_equal(px[int(oy), int(ox)], figures.GREY)
    # no-data cells of the left image are dark red
    x0, y0 = fig.extra["tiles_x"][0], fig.extra["tiles_y"]
    assert tuple(px[y0 + 2, x0 + 2]) == figures.NO_DATA


# ------------------------------------------------------------------------------------------------
# pose plot


def test_pose_plot_vectors_and_histograms():
    rng = np.random.default_rng(3)
    m = np.stack(np.meshgrid([25.0, 65.0, 105.0], [25.0, 60.0, 95.0]), -1).reshape(9, 2)  # well apart
    rb = rng.normal(0, 2.0, (9, 2))
    ra = rng.normal(0, 0.05, (9, 2))
    status = ["ok"] * 8 + ["rejected-outlier"]
    fig = figures.pose_plot(
        _photo(), None, list("ABCDEFGHI"), m, rb, ra, status, picture="P", magnify=5, magnify_after=100
    )
    px = _png(fig)
    for k in range(8):
        p = np.array(fig.xy(*m[k]))
        for res, f, key, colour in (
            (rb, 5, "tips_before", figures.BEFORE),
            (ra, 100, "tips_after", figures.AFTER),
        ):
            tip = p - f * fig.zoom * res[k]
            assert np.allclose(fig.extra[key][k], tip)
            if 2 <= tip[0] < px.shape[1] - 2 and 2 <= tip[1] < px.shape[0] - 2:
                assert _near(px, tip, colour, r=2)
    assert np.isnan(fig.extra["tips_before"][8]).all()
    (eb, cb), (ea, ca) = fig.extra["hist"]
    assert cb.sum() == 8 and ca.sum() == 8
    assert np.array_equal(cb, np.histogram(np.hypot(*rb[:8].T), bins=eb)[0])


def test_pose_plot_without_photo():
    fig = figures.pose_plot(None, None, ["A"], [[10, 10]], [[1, 1]], [[0.1, 0]], ["ok"], shape=(64, 80))
    _png(fig)


# ------------------------------------------------------------------------------------------------
# batch summary and contact sheets


def test_batch_summary_bars_are_proportional():
    rb, ra = [3.0, 2.0, np.nan], [0.06, 0.1, np.nan]
    sel, fnd = [12, 10, 8], [12, 6, 0]
    fig = figures.batch_summary(["P1", "P2", "P3"], rb, ra, sel, fnd, ["ok", "ok", "failed"])
    px = _png(fig)
    bars = fig.extra["bars"]
    (_, _, _, base1), (_, _, _, base2) = fig.extra["axes"]
    # linear count axis: heights in proportion to the counts
    h = {key: base2 - bars[(1, key)][1] for key in ("selected", "found")}
    assert h["found"] / h["selected"] == pytest.approx(6 / 10, abs=0.02)
    # log rms axis: equal ratios give equal height differences
    lo_hi = (bars[(0, "rms_before")][1], bars[(1, "rms_before")][1], bars[(0, "rms_after")][1])
    ratio = (lo_hi[1] - lo_hi[0]) / (lo_hi[2] - lo_hi[0])
    assert ratio == pytest.approx(math.log10(3 / 2) / math.log10(3 / 0.06), abs=0.02)
    for (_k, key), (x, top) in bars.items():
        colour = {"rms_before": figures.BEFORE, "rms_after": figures.AFTER}.get(key)
        if colour:
            assert tuple(px[int(top) + 3, int(x)]) == colour
    assert (2, "rms_before") not in bars and (2, "found") not in bars


def test_contact_sheet_and_surface_tile():
    from types import SimpleNamespace

    corr = SimpleNamespace(surface=_gaussian_surface(), peak_index=(6, 4), subpixel=(0.3, -0.4))
    rgb = figures.surface_tile(corr)
    k = rgb.shape[0] // 11
    assert rgb.shape == (11 * k, 11 * k, 3)
    assert _near(rgb, ((4 - 0.4) * k + (k - 1) / 2, (6 + 0.3) * k + (k - 1) / 2), figures.PEAK)
    img = np.random.default_rng(0).uniform(0, 1, (25, 25))
    fig = figures.contact_sheet([("a", img, None), ("b", img, img > 0.5), ("c", rgb)], title="t")
    _png(fig)
    assert fig.size[0] >= 2 * 160 and fig.size[1] >= 2 * 160


# ------------------------------------------------------------------------------------------------
# the commands that write figures (working directory of test_cli_register: one landmark, FITS photo)

from test_cli_register import LMK, PIC, invoke  # noqa: E402
from test_cli_register import world as world  # noqa: E402, F401  (the fixture, by name)

from spctool.formats.table import LandmarkTable  # noqa: E402


def _geometry(path):
    import json

    with Image.open(path) as img:
        img.load()
        return json.loads(img.text["spctool"]), np.asarray(img.convert("RGB"))


def test_correlate_panel_peak_sits_at_the_table_offset(request, tmp_path):
    world = request.getfixturevalue("world")
    root, _, _ = world
    res = invoke(
        root,
        "correlate",
        PIC,
        LMK,
        "--spacing",
        "2",
        "--panels",
        tmp_path / "p",
        "--sheet",
        tmp_path / "sheet.png",
    )
    assert res.exit_code == 0, res.output
    t = LandmarkTable.parse_text(res.stdout)
    assert t["status"] == ["ok"]
    geo, px = _geometry(tmp_path / "p" / f"{LMK}_{PIC}_correlate-panel.png")
    assert px.shape[1] > 600 and px.shape[0] > 250 and px.std() > 5
    # offset_x runs along UX = surface rows, offset_y along UY = columns, in cells; grid index = K + offset/n
    k = 5
    col, row = k + t["offset_y"][0] / 2, k + t["offset_x"][0] / 2
    ox, oy = geo["surface_origin"]
    x, y = ox + col * geo["cell"], oy + row * geo["cell"]
    assert (x, y) == pytest.approx(tuple(geo["peak"]), abs=0.01)  # the table has 4 decimals
    assert _near(px, (x, y), figures.PEAK)
    _, sheet = _geometry(tmp_path / "sheet.png")
    assert np.any(np.all(sheet == figures.PEAK, axis=-1))


def test_register_panels_and_solve_pose_plot(request, tmp_path):
    world = request.getfixturevalue("world")
    root, sc, _ = world
    reg = tmp_path / "reg.txt"
    res = invoke(root, "register", PIC, LMK, "--steps", "2,1", "--panels", tmp_path / "p", "-o", reg)
    assert res.exit_code == 0, res.output
    geo, px = _geometry(tmp_path / "p" / f"{LMK}_{PIC}_panel.png")
    assert geo["peak"] is not None and _near(px, geo["peak"], figures.PEAK)
    out = tmp_path / "pose.png"
    res = invoke(root, "solve-pose", PIC, "--measurements", reg, "--min-landmarks", "1", "--plot", out)
    assert res.exit_code == 0, res.output
    geo, px = _geometry(out)
    assert px.shape[1] > sc.camera.npx and px.std() > 5 and geo["magnify"] >= 1
    # one reference vector per magnification, drawn at that magnification in its set's colour
    for when, mag, colour in (
        ("before", geo["magnify"], figures.BEFORE),
        ("after", geo["magnify_after"], figures.AFTER),
    ):
        ref, length, x, y = geo[f"reference_{when}"]
        assert length == pytest.approx(ref * mag * geo["zoom"]) and 10 <= length <= 330
        assert _near(px, (x + length / 2, y), colour)


def test_predict_and_extract_sheets(request, tmp_path):
    world = request.getfixturevalue("world")
    root, _, _ = world
    for cmd in ("predict", "extract"):
        res = invoke(root, cmd, PIC, LMK, "--sheet", tmp_path / f"{cmd}.png")
        assert res.exit_code == 0, res.output
        _, px = _geometry(tmp_path / f"{cmd}.png")
        assert px.shape[0] >= 160 and px.std() > 5


def test_batch_writes_the_summary_figure_and_plots(tmp_path):
    import math

    from batch_world import make_world

    world = tmp_path / "world"
    make_world(world, n_pictures=2, n_landmarks=5)
    out = tmp_path / "out"
    res = invoke(world, "batch", "--out-dir", out, "--plots")
    assert res.exit_code == 0, res.output
    t = [ln.split() for ln in res.stdout.splitlines() if ln.strip() and not ln.startswith("#")]
    head, rows = t[0], t[1:]
    geo, px = _geometry(out / "BATCH_SUMMARY.png")
    assert px.shape[0] > 400 and px.std() > 5
    x0, y0, x1, y1 = geo["rms_box"]
    lo, hi = geo["rms_ylim"]
    for k, row in enumerate(rows):
        # the before/after bars reach the table's rms on the log axis (computed here from the table)
        for key, colour, dx in (
            ("rms_before_px", figures.BEFORE, -0.2),
            ("rms_after_px", figures.AFTER, 0.2),
        ):
            v = float(row[head.index(key)])
            top = y1 - (math.log10(v) - math.log10(lo)) / (math.log10(hi) - math.log10(lo)) * (y1 - y0)
            x = geo["slot_x"][k] + dx * (x1 - x0) / len(rows)
            assert tuple(px[int(top) + 2, int(x)]) == colour and tuple(px[int(top) - 2, int(x)]) != colour
    for pic in (r[0] for r in rows):
        for kind in ("register", "pose"):
            _, p = _geometry(out / "PLOTS" / f"{pic}.{kind}.png")
            assert p.shape[0] > 150 and p.std() > 5


def test_zoom_enlarges_out_dir_images_cell_by_cell(request, tmp_path):
    world = request.getfixturevalue("world")
    root = world[0]
    for cmd, stem in (("predict", "predicted"), ("correlate", "surface")):
        for zoom in ("1", "4"):
            out = tmp_path / f"{cmd}{zoom}"
            res = invoke(root, cmd, PIC, LMK, "--out-dir", out, "--image-format", "png", "--zoom", zoom)
            assert res.exit_code == 0, res.output
        with Image.open(tmp_path / f"{cmd}1" / f"{LMK}_{PIC}_{stem}.png") as a:
            small = np.asarray(a)
        with Image.open(tmp_path / f"{cmd}4" / f"{LMK}_{PIC}_{stem}.png") as b:
            big = np.asarray(b)
        assert big.shape == (4 * small.shape[0], 4 * small.shape[1])
        assert np.array_equal(big[::4, ::4], small) and np.array_equal(big[3::4, 3::4], small)
