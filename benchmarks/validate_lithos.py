#!/usr/bin/env python
"""Validation of ``spctool lithos`` against known truth (issue #38, "Must show"), on two worlds:

1. **simulate** (spctool's own renderer): the example spec with three maplets of 1 m cells,
   ``[maplets] write_truth = true``, ``[terrain.albedo] contrast = 0.3`` and five pictures with the Sun
   from N, E, S, W and overhead; every picture is navigated first (``navigate --output``: its pose
   solved against the landmarks as simulated), then the starting maplets are made by ``make-maplets
   --keep-frame`` from the world's shape model (far coarser than the truth).  The truth maplet is
   the truth patch (``TRUTHFILES/``, ``truth_factor`` times finer) sampled at the maplet's nodes.
2. **independent** (trimesh + Embree, :mod:`spctool.sim.independent`, Lambert, faceted truth, six
   pictures with 3 px a-priori errors): every picture is navigated first against the maplets the world
   writes, which are the truth; the starting maplets are them smoothed by a Gaussian of 4 cells with
   a uniform albedo.

Prints, per maplet, the height rms against the truth (cells) before and after ``lithos``, the gain,
the albedo correlation with the truth and the mean NCC before/after; on the independent world also
the two-pass navigation (``navigate``) of every picture against the starting and the refined maplets,
rms distance of the registered landmarks to their true pixels.  Usage::

    python benchmarks/validate_lithos.py OUTDIR            # both worlds (~5 min on a quiet machine)
    python benchmarks/validate_lithos.py OUTDIR independent

Not part of ``run.py`` (it builds worlds); the figures are quoted in the README and the report.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np


def _cli(*args):
    from spctool.cli.main import cli

    try:
        cli.main([str(a) for a in args], standalone_mode=False)
    except SystemExit as exc:  # pragma: no cover - a failed command
        if exc.code:
            raise


def _spec(path: Path):
    import io
    from contextlib import redirect_stdout

    buf = io.StringIO()
    with redirect_stdout(buf):
        _cli("simulate", "--example")
    text = buf.getvalue()
    head = text[: text.index("[[pictures]]")]
    head = head.replace("count = 12", "count = 3").replace("write_truth = false", "write_truth = true")
    head = head.replace("scale_km = 0.0005", "scale_km = 0.001")
    lines = head.splitlines()
    in_albedo = False
    for i, ln in enumerate(lines):
        if ln.startswith("["):
            in_albedo = ln.strip() == "[terrain.albedo]"
        elif in_albedo and ln.startswith("contrast ="):
            lines[i] = "contrast = 0.3"
    pics = ""
    for slat, slon, vlat, vlon in [(55, 20, 18, 28), (10, 65, 2, 12), (-35, 20, 18, 12), (10, -25, 2, 28),
                                   (20, 30, 10, 20)]:
        pics += (f"[[pictures]]\naim_lat_deg = 10.0\naim_lon_deg = 20.0\nview_lat_deg = {vlat}\n"
                 f"view_lon_deg = {vlon}\nrange_km = 1.9\nsun_lat_deg = {slat}\nsun_lon_deg = {slon}\n"
                 'format = "dat"\n\n')
    path.write_text("\n".join(lines) + "\n" + pics)


def _navigate_first(root: Path, *extra):
    """Every picture's pose solved by ``navigate`` against the world's own maplets (SUM rewritten)."""
    for sum_path in sorted((root / "SUMFILES").glob("*.SUM")):
        new = f"SUMFILES/{sum_path.stem}.SUM.solved"
        _cli("-q", "-C", root, "navigate", sum_path.stem, "--output", new, "-o", "/dev/null", *extra)
        if (root / new).exists():
            (root / new).replace(sum_path)


def _truth_on_grid(m, t):
    f = round(m.scale / t.scale)
    idx = t.qsz + f * (np.arange(2 * m.qsz + 1) - m.qsz)
    return t.heights[np.ix_(idx, idx)] / f, t.albedo[np.ix_(idx, idx)]


def _report(root: Path, start: dict, doc: dict):
    from spctool.formats.maplet import read_map

    for m in doc["meta"]["maplets"] if "meta" in doc else doc["maplets"]:
        name = m["name"]
        new = read_map(root / "MAPFILES" / f"{name}.MAP")
        truth = read_map(root / "TRUTHFILES" / f"{name}.MAP")
        th, ta = _truth_on_grid(new, truth)
        v = new.valid
        e0 = float(np.sqrt(np.mean((start[name] - th)[v] ** 2)))
        e1 = float(np.sqrt(np.mean((new.heights - th)[v] ** 2)))
        corr = float(np.corrcoef(new.albedo[v], ta[v])[0, 1])
        print(f"{root.name:12s} {name}  height rms {e0:.3f} -> {e1:.3f} cells ({e0 / e1:.1f}x)  albedo corr "
              f"{corr:.3f}  NCC {m['ncc_before']:.3f} -> {m['ncc_after']:.3f}  {m['status']}", flush=True)


def _lithos(root: Path, *extra):
    import io
    from contextlib import redirect_stdout

    from spctool.formats.maplet import read_map

    start = {p.stem: read_map(p).heights for p in (root / "MAPFILES").glob("*.MAP")}
    buf = io.StringIO()
    with redirect_stdout(buf):
        _cli("-q", "-C", root, "lithos", "--force", "--json", *extra)
    _report(root, start, json.loads(buf.getvalue()))


def simulated(out: Path):
    root = out / "simulated"
    _spec(out / "lithos-validation.toml")
    _cli("-q", "simulate", out / "lithos-validation.toml", root)
    names = sorted(p.stem for p in (root / "MAPFILES").glob("*.MAP"))
    # SPC's order: the pictures are navigated first (poses solved against the landmarks as simulated),
    # then the maplets are remade from the shape and refined from the pictures at the solved poses
    _navigate_first(root)
    _cli("-q", "-C", root, "make-maplets", *names, "--keep-frame", "--overwrite")
    _lithos(root)


def independent(out: Path):
    from scipy.ndimage import gaussian_filter

    from spctool.formats.maplet import read_map, write_map
    from spctool.sim.independent import IndependentSpec, build_world

    root = out / "independent"
    build_world(root, IndependentSpec(n_side=2, apriori_px=(3.0,) * 6))
    _navigate_first(root, "--photometry", "lambert")
    (root / "TRUTHFILES").mkdir(exist_ok=True)
    for p in sorted((root / "MAPFILES").glob("*.MAP")):
        m = read_map(p)
        write_map(root / "TRUTHFILES" / p.name, m)
        m.heights = np.where(m.valid, gaussian_filter(m.heights, 4.0, mode="nearest"), 0.0)
        m.albedo = np.where(m.valid, 1.0, 0.0)
        write_map(p, m)
    import shutil

    shutil.copytree(root, out / "independent-start", dirs_exist_ok=True)
    _lithos(root, "--photometry", "lambert")
    for r in (out / "independent-start", root):
        _navigation(r)


def _navigation(root: Path):
    """Two-pass navigation of every picture (``navigate``, Lambert prediction) against the maplets of
    ``root``; rms and max of the registered landmarks' distance to their true pixels (TRUTH.json)."""
    import io
    from contextlib import redirect_stdout

    truth = json.loads((root / "TRUTH.json").read_text())
    errs = []
    for pic in truth["pictures"]:
        buf = io.StringIO()
        with redirect_stdout(buf):
            try:
                _cli("-q", "-C", root, "navigate", pic["name"], "--json", "--photometry", "lambert")
            except (Exception, SystemExit):  # noqa: BLE001 - a failed pose still prints its table
                pass
        text = buf.getvalue()
        if not text.strip():
            continue
        for row in json.loads(text)["landmarks"]:
            if row["status"] == "ok" and row["name"] in pic["pixels"]:
                t = pic["pixels"][row["name"]]
                errs.append(float(np.hypot(row["sample"] - t[0], row["line"] - t[1])))
    e = np.array(errs)
    rms = float(np.sqrt(np.mean(e * e)))
    print(f"{root.name:20s} navigate two-pass: {e.size} landmarks registered, rms {rms:.4f} px, "
          f"max {e.max():.4f} px against the true pixels", flush=True)


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if not argv:
        print(__doc__)
        return 2
    out = Path(argv[0])
    out.mkdir(parents=True, exist_ok=True)
    which = argv[1:] or ["simulated", "independent"]
    for w in which:
        {"simulated": simulated, "independent": independent}[w](out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
