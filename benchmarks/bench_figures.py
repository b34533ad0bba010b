"""Figure drawing speed (spctool.figures): the PNGs of register --overlay / --panels and solve-pose --plot.

Setup: a 1024 x 1024 photo with 500 landmarks (shifts of a few pixels, a tenth failed); an 11 x 11
correlation surface with 49 x 49 maplet images.  Measured: drawing and PNG-encoding each figure, best of
three.  Targets: the overlay and the pose plot of 500 landmarks in <= 1 s (PNG encoding of a
1024-px photo dominates; with Pillow's optimize=True it was 3.7 s), one landmark panel in <= 0.1 s
(panels for 100 landmarks add seconds, not minutes).
"""

from __future__ import annotations

import time

import numpy as np

from spctool import figures


def _photo(n=1024):
    ln, s = np.mgrid[0:n, 0:n]
    return 2000.0 + 800.0 * np.sin(s / 23.0) * np.cos(ln / 31.0)


def _best(fn, repeats=3):
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def bench_overlay_500():
    rng = np.random.default_rng(0)
    photo = _photo()
    a = rng.uniform(20, 1000, (500, 2))
    m = a + rng.normal(0, 2.0, (500, 2))
    status = ["ok"] * 450 + ["not-found"] * 50
    m[450:] = np.nan
    names = [f"LM{i:04d}" for i in range(500)]
    t = _best(lambda: figures.register_overlay(photo, None, names, a, m, status, picture="P").png())
    return t, "s", t <= 1.0


def bench_pose_plot_500():
    rng = np.random.default_rng(1)
    m = rng.uniform(20, 1000, (500, 2))
    rb, ra = rng.normal(0, 3, (500, 2)), rng.normal(0, 0.1, (500, 2))
    names = [f"LM{i:04d}" for i in range(500)]
    photo = _photo()
    t = _best(lambda: figures.pose_plot(photo, None, names, m, rb, ra, ["ok"] * 500, picture="P").png())
    return t, "s", t <= 1.0


def bench_panel():
    rng = np.random.default_rng(2)
    img = rng.uniform(0, 1, (49, 49))
    surface = rng.uniform(-0.2, 0.9, (11, 11))

    def run():
        return figures.landmark_panel(
            "LM", "P", img, img, surface, peak_index=(5, 6), subpixel=(0.1, -0.2), rho=0.9, status="ok"
        ).png()

    t = _best(run)
    return t, "s", t <= 0.1


BENCHMARKS = [
    ("figures: register overlay, 1024 px photo, 500 landmarks", "<= 1 s", bench_overlay_500),
    ("figures: solve-pose plot, 1024 px photo, 500 landmarks", "<= 1 s", bench_pose_plot_500),
    ("figures: one landmark panel (49x49 images, 11x11 surface)", "<= 0.1 s", bench_panel),
]
