"""A world of ``spctool simulate`` for the "Find heights" checks against truth (issue #38): the example
spec with ``[maplets] write_truth = true``, 1 m maplet cells (``truth_factor`` 3: 1/3 m truth cells),
``[terrain.albedo] contrast = 0.3`` and five pictures with the Sun from N, E, S, W and overhead
(``benchmarks/validate_lithos.py``'s spec; there three maplets and 768² photos, pictures navigated).
Here ``count`` maplets and ``npx``² photos; the pictures' SUM poses are set to the true ones
(navigated perfectly: one maplet is too few for ``navigate``), then the starting maplets are made by
``make-maplets --keep-frame`` from the world's shape model (far coarser than the truth).

The truth a maplet is judged against is the truth patch at the **maplet's resolution**, as
``simulate`` makes its own maplets from it (Gaussian σ = ``smoothing_cells`` maplet cells, sampled at
the nodes): a 1 m grid cannot hold the 1/3–1 m roughness of the truth, and the point-sampled truth
differs from it by 0.08–0.09 cells rms — a floor no maplet of this scale can go below
(:func:`truth_on_grid` gives both).
"""

from __future__ import annotations

import io
import json
from contextlib import redirect_stdout
from pathlib import Path

import numpy as np
from scipy.ndimage import gaussian_filter

PICTURES = [(55, 20, 18, 28), (10, 65, 2, 12), (-35, 20, 18, 12), (10, -25, 2, 28), (20, 30, 10, 20)]


def cli(*args) -> str:
    """Run spctool in this process; stdout returned; a failing command raises."""
    from spctool.cli.main import cli as group

    buf = io.StringIO()
    with redirect_stdout(buf):
        try:
            group.main([str(a) for a in args], standalone_mode=False)
        except SystemExit as exc:
            if exc.code:
                raise
    return buf.getvalue()


#: (lat, lon) of the three maplets the automatic placement gives the validation world (768² photos)
POSITIONS = {
    "SM0001": (-2.206596, 5.439032),
    "SM0002": (14.549018, 31.193867),
    "SM0003": (12.956139, 9.321401),
}


def spec_text(count: int = 3, npx: int = 768, positions=None) -> str:
    text = cli("simulate", "--example")
    head = text[: text.index("[[pictures]]")]
    head = head.replace("count = 12", f"count = {count}").replace("write_truth = false", "write_truth = true")
    head = head.replace("scale_km = 0.0005", "scale_km = 0.001")
    head = head.replace("npx = 768", f"npx = {npx}").replace("nln = 768", f"nln = {npx}")
    if positions:
        head = head.replace("positions = []", "positions = " + repr([list(p) for p in positions]))
    lines = head.splitlines()
    section = ""
    for i, ln in enumerate(lines):
        if ln.startswith("["):
            section = ln.strip()
        elif section == "[terrain.albedo]" and ln.startswith("contrast ="):
            lines[i] = "contrast = 0.3"
    pics = ""
    for slat, slon, vlat, vlon in PICTURES:
        pics += (f"[[pictures]]\naim_lat_deg = 10.0\naim_lon_deg = 20.0\nview_lat_deg = {vlat}\n"
                 f"view_lon_deg = {vlon}\nrange_km = 1.9\nsun_lat_deg = {slat}\nsun_lon_deg = {slon}\n"
                 'format = "dat"\n\n')
    return "\n".join(lines) + "\n" + pics


def true_poses(root: Path) -> None:
    """Every SUM's SCOBJ and camera axes set to the true pose of TRUTH.json."""
    from spctool.formats.sumfile import read_sum, write_sum

    truth = json.loads((root / "TRUTH.json").read_text())
    for pic in truth["pictures"]:
        path = root / "SUMFILES" / f"{pic['name']}.SUM"
        s = read_sum(path)
        rot = np.asarray(pic["true"]["rotation"], dtype=np.float64)
        s.scobj = np.asarray(pic["true"]["scobj"], dtype=np.float64)
        s.cx, s.cy, s.cz = rot[0], rot[1], rot[2]
        write_sum(path, s)


def build(root: Path, count: int = 1, npx: int = 512, positions=None) -> list[str]:
    """The world in ``root`` (module docstring); returns the landmark names."""
    root = Path(root)
    root.parent.mkdir(parents=True, exist_ok=True)
    spec = root.parent / f"{root.name}.toml"
    spec.write_text(spec_text(count, npx, positions))
    cli("-q", "simulate", spec, root)
    true_poses(root)
    names = sorted(p.stem for p in (root / "MAPFILES").glob("*.MAP"))
    cli("-q", "-C", root, "make-maplets", *names, "--keep-frame", "--overwrite")
    return names


def truth_on_grid(m, t, smoothing_cells: float = 0.5):
    """(heights, albedo) of the truth patch ``t`` at the nodes of the maplet ``m`` (cells of ``m``):
    ``matched`` — smoothed as simulate makes its maplets (σ = ``smoothing_cells`` maplet cells) — and
    ``point`` — sampled without smoothing; a dict of both."""
    f = round(m.scale / t.scale)
    idx = t.qsz + f * (np.arange(2 * m.qsz + 1) - m.qsz)
    sig = smoothing_cells * f
    hs = gaussian_filter(t.heights, sig, mode="nearest")
    as_ = gaussian_filter(t.albedo, sig, mode="nearest")
    grid = np.ix_(idx, idx)
    return {"matched": (hs[grid] / f, as_[grid]), "point": (t.heights[grid] / f, t.albedo[grid])}


def plane_rms(e, mask) -> float:
    """rms of the best-fit plane of ``e`` over ``mask`` (the part ``keep_plane`` keeps from the start)."""
    r, c = np.nonzero(mask)
    a = np.stack([np.ones(r.size), r, c], axis=1).astype(float)
    coef, *_ = np.linalg.lstsq(a, e[mask], rcond=None)
    return float(np.sqrt(np.mean((a @ coef) ** 2)))
