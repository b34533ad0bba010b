#!/usr/bin/env python
"""Validation of ``spctool lithos`` against known truth (issue #38, "Must show"), on two worlds:

1. **simulate** (spctool's own renderer): the example spec with three maplets of 1 m cells,
   ``[maplets] write_truth = true``, ``[terrain.albedo] contrast = 0.3`` and five pictures with the Sun
   from N, E, S, W and overhead; every picture is navigated first (``navigate --output``: its pose
   solved against the landmarks as simulated), then the starting maplets are made by ``make-maplets
   --keep-frame`` from the world's shape model (far coarser than the truth).  The truth maplet is
   the truth patch (``TRUTHFILES/``, ``truth_factor`` times finer) at the maplet's nodes, twice:
   ``matched``, smoothed as simulate makes its own maplets (σ = 0.5 maplet cells: what a 1 m grid can
   hold), and ``point``, sampled without smoothing (its 1/3–1 m roughness, 0.08–0.09 cells rms, is a
   floor no maplet of this scale goes below).  Spec and helpers: ``tests/lithos_sim_world.py``.
2. **independent** (trimesh + Embree, :mod:`spctool.sim.independent`, Lambert, faceted truth, six
   pictures with 3 px a-priori errors): every picture is navigated first against the maplets the world
   writes, which are the truth; the starting maplets are them smoothed by a Gaussian of 4 cells with
   a uniform albedo.

Prints, per maplet, the height rms against the truth (cells) before and after ``lithos``, the gain,
the albedo correlation with the truth, the starting map's best-fit-plane error (kept by
``keep_plane``) and the mean NCC before/after; on both worlds the two-pass navigation (``navigate``)
of every picture against the starting and the refined maplets (same pictures), rms distance of the
registered landmarks to their true pixels.  Usage::

    python benchmarks/validate_lithos.py OUTDIR            # both worlds (~5 min on a quiet machine)
    python benchmarks/validate_lithos.py OUTDIR independent

Not part of ``run.py`` (it builds worlds); the figures are quoted in the README and the report.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # lithos_sim_world


def _cli(*args):
    from spctool.cli.main import cli

    try:
        cli.main([str(a) for a in args], standalone_mode=False)
    except SystemExit as exc:  # pragma: no cover - a failed command
        if exc.code:
            raise


def _spec(path: Path):
    from lithos_sim_world import spec_text

    path.write_text(spec_text(count=3, npx=768))


def _navigate_first(root: Path, *extra):
    """Every picture's pose solved by ``navigate`` against the world's own maplets (SUM rewritten)."""
    for sum_path in sorted((root / "SUMFILES").glob("*.SUM")):
        new = f"SUMFILES/{sum_path.stem}.SUM.solved"
        _cli("-q", "-C", root, "navigate", sum_path.stem, "--output", new, "-o", "/dev/null", *extra)
        if (root / new).exists():
            (root / new).replace(sum_path)


def _report(root: Path, start: dict, doc: dict):
    """Per maplet: height rms against the truth before/after and the gain, albedo correlation, mean NCC.
    On a simulated world the truth is taken at the maplet's resolution (``matched``: as simulate makes
    its maplets) and point-sampled (``point``, with the roughness no grid of this scale holds); the
    starting map's best-fit plane error (``keep_plane`` keeps it) is printed beside."""
    from lithos_sim_world import plane_rms, truth_on_grid

    from spctool.formats.maplet import read_map

    for m in doc["meta"]["maplets"] if "meta" in doc else doc["maplets"]:
        name = m["name"]
        new = read_map(root / "MAPFILES" / f"{name}.MAP")
        truth = read_map(root / "TRUTHFILES" / f"{name}.MAP")
        v = new.valid
        if round(new.scale / truth.scale) > 1:
            grids = truth_on_grid(new, truth)
        else:
            grids = {"truth": (truth.heights, truth.albedo)}
        for kind, (th, ta) in grids.items():
            e0 = float(np.sqrt(np.mean((start[name] - th)[v] ** 2)))
            e1 = float(np.sqrt(np.mean((new.heights - th)[v] ** 2)))
            corr = float(np.corrcoef(new.albedo[v], ta[v])[0, 1])
            print(f"{root.name:12s} {name} {kind:7s} height rms {e0:.3f} -> {e1:.3f} cells ({e0 / e1:.1f}x)  "
                  f"albedo corr {corr:.3f}  start plane {plane_rms(start[name] - th, v):.3f}  "
                  f"NCC {m['ncc_before']:.3f} -> {m['ncc_after']:.3f}  {m['status']} "
                  f"(first pass: {m['history'][0].get('first_pixels', '-') if m['history'] else '-'})",
                  flush=True)


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
    import shutil

    shutil.copytree(root, out / "simulated-start", dirs_exist_ok=True)
    _lithos(root)
    for r in (out / "simulated-start", root):
        _navigation(r)


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
        _navigation(r, "--photometry", "lambert")


def _navigation(root: Path, *extra):
    """Two-pass navigation of every picture (``navigate``; ``extra`` options, e.g. a Lambert
    prediction) against the maplets of ``root``; rms and max of the registered landmarks' distance to
    their true pixels (TRUTH.json: per picture on the independent world, per landmark on simulate's)."""
    import io
    from contextlib import redirect_stdout

    truth = json.loads((root / "TRUTH.json").read_text())
    rows = [lm for lm in truth.get("landmarks", []) if isinstance(lm, dict)]
    by_landmark = {lm["name"]: lm.get("pixels", {}) for lm in rows}
    errs = []
    for pic in truth["pictures"]:
        true_px = pic.get("pixels") or {n: (p[pic["name"]]["sample"], p[pic["name"]]["line"])
                                         for n, p in by_landmark.items() if pic["name"] in p}
        buf = io.StringIO()
        with redirect_stdout(buf):
            try:
                _cli("-q", "-C", root, "navigate", pic["name"], "--json", *extra)
            except (Exception, SystemExit):  # noqa: BLE001 - a failed pose still prints its table
                pass
        text = buf.getvalue()
        if not text.strip():
            continue
        for row in json.loads(text)["landmarks"]:
            if row["status"] == "ok" and row["name"] in true_px:
                t = true_px[row["name"]]
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
