"""SPC's GEOMETRY step on a working directory: gather every registered measurement, refine, write back.

map-refinement.md §1 ("What is written", "Batch"); the numerics are :func:`spctool.stages.bundle.
solve_bundle`.  This module is the I/O around it, shared by ``spctool geometry`` and ``batch --rounds``:

* :func:`gather` — the pictures (PICTLIST's active ones, or those named), their SUM poses and
  SIGMA_VSO/SIGMA_PTG, the measurements (SUM LANDMARKS rows, a ``*`` row not used; or, with
  ``tables``, the register tables ``<PIC>.register.txt`` whose ``sigma_sample``/``sigma_line``/``rho_sl``
  give each measurement's covariance) and the landmarks (LMK VLM, SIGMA_LMK or else SIGKM).
  INIT_LITHOS weights (spc-formats.md §6: applied as √value, i.e. the information scales by the
  value; which entry weighs what is not documented — spctool's reading, [inf]): ``PICWTS= WB, WL, WC,
  WS, WT`` — WS scales the spacecraft-position prior, WC the pointing prior, WL the landmark
  measurements; ``LMKWTS= WB, WO, WL, WR`` — WB scales the landmark-position prior (WO, WL: overlaps
  and limbs, which spctool does not use yet).
* :func:`write_back` — atomically, each replaced file keeping a ``.bak``: LMK VLM, SIGMA_LMK (posterior
  1σ, km, scaled by chi2/dof when above 1 as every sigma written and reported), RMSLMK
  (rms post-fit residual of the landmark's used measurements, **pixels** — spctool's documented choice;
  SPC's unit is not public) and the PICTURES section (one row per picture that measured it: the measured
  sample/line, ``*`` when not used); the MAP header's V set to the new VLM (real*4; every other byte
  kept); the SUM's SCOBJ, CX/CY/CZ, SIGMA_VSO/SIGMA_PTG and its LANDMARKS rows' flags (``*`` on an
  outlier).
* :func:`residuals_table`, :func:`lmkvecs_text`, :func:`formal_summary` — the reports in the spirit of
  SPC's RESIDUALS.TXT, LMKVECS.TXT and get80's formal uncertainty (the best 80 % of landmarks).
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from spctool.batch.layout import TABLES_DIR
from spctool.errors import SpcFormatError, SpcUsageError
from spctool.formats import atomic, guard
from spctool.formats.workdir import WorkDir
from spctool.stages.bundle import BundleProblem, BundleResult

__all__ = [
    "RefineInputs",
    "gather",
    "write_back",
    "residuals_table",
    "lmkvecs_text",
    "formal_summary",
    "summary_table",
]

#: the register table of picture P in a tables folder (``batch``'s ``tables/`` or ``register -o``)
TABLE_PATTERN = "{picture}.register.txt"


@dataclass
class RefineInputs:
    """A bundle problem and the files it came from (for writing back)."""

    problem: BundleProblem
    pictures: dict  # name -> Picture (SUM)
    sum_paths: dict  # name -> Path (where the refined SUM is written)
    landmarks: dict  # name -> Landmark (LMK)
    lmk_paths: dict  # name -> Path
    source: str  # "sum" or "tables"
    notes: list[str] = field(default_factory=list)
    weights: dict = field(default_factory=dict)
    #: (SUM read, Picture) of the pictures whose LANDMARKS rows were the measurements
    row_sources: list = field(default_factory=list)


def _weights(settings) -> dict:
    """The INIT_LITHOS weights spctool applies (module docstring), 1 when absent."""
    out = {"position": 1.0, "pointing": 1.0, "measurements": 1.0, "landmark_prior": 1.0}
    if settings is None:
        return out
    pic = settings.get_floats("PICWTS=") or []
    if len(pic) >= 4:
        out["measurements"], out["pointing"], out["position"] = float(pic[1]), float(pic[2]), float(pic[3])
    lmk = settings.get_floats("LMKWTS=") or []
    if lmk:
        out["landmark_prior"] = float(lmk[0])
    for k, v in out.items():
        if not (math.isfinite(v) and v >= 0):
            raise SpcUsageError(f"INIT_LITHOS weight for {k} must be a non-negative number, got {v}")
    return out


def _scaled_sigma(sig, weight) -> np.ndarray:
    """σ of a prior whose information is multiplied by ``weight`` (0 removes it: σ = inf)."""
    s = np.asarray(sig, dtype=np.float64)
    if weight == 0:
        return np.full_like(s, np.inf)
    return s / math.sqrt(weight)


def _table_rows(path: Path, picture: str):
    """(names, pixels (N, 2), usable (N,), covariance (N, 2, 2) or None) of a register table."""
    from spctool.formats.table import read_table

    table = read_table(path)
    if table.picture and table.picture.strip() != picture:
        raise SpcFormatError(path, None, f"a register table of picture {picture} (it is for {table.picture})")
    try:
        pix = np.stack(
            [np.asarray(table["sample"], dtype=np.float64), np.asarray(table["line"], dtype=np.float64)],
            axis=1,
        )
    except (KeyError, TypeError, ValueError):
        raise SpcFormatError(path, None, "a landmark table with numeric sample and line columns") from None
    status = [str(s) for s in table["status"]] if "status" in table else ["ok"] * len(table)
    usable = np.array([s == "ok" for s in status], dtype=bool) & np.all(np.isfinite(pix), axis=1)
    cov = None
    if all(c in table for c in ("sigma_sample", "sigma_line", "rho_sl")):
        ss, sl, rho = (
            np.asarray(table[c], dtype=np.float64) for c in ("sigma_sample", "sigma_line", "rho_sl")
        )
        cov = np.empty((len(ss), 2, 2))
        cov[:, 0, 0], cov[:, 1, 1] = ss * ss, sl * sl
        cov[:, 0, 1] = cov[:, 1, 0] = rho * ss * sl
    return [n.strip() for n in table.names], pix, usable, cov


def gather(
    wd: WorkDir,
    settings=None,
    *,
    pictures=None,
    tables=None,
    sigma_px: float = 0.25,
    sigma_floor_px: float = 0.05,
    ignore_in_vlm=(),
    from_batch=None,
) -> RefineInputs:
    """Read every measurement of ``pictures`` and the landmarks they measured (module docstring).

    ``tables`` — a folder of register tables (``<PIC>.register.txt``, or a batch output whose
    ``TABLES/`` holds them); measurements then carry their covariance (+ ``sigma_floor_px``² I), the
    others σ = ``sigma_px``.  ``ignore_in_vlm`` — pictures whose measurements do not constrain V.  A
    picture named twice in ``pictures`` is a :class:`SpcUsageError` (its measurements would count twice
    and its SUM be written twice); one listed twice in PICTLIST is used once, with a note.
    ``from_batch`` — a ``batch --out-dir``: its pictures (those it wrote a SUM for, in PICTLIST order),
    their SUMs (the batch's solved poses and measured LANDMARKS rows) and its register tables.  The
    files written back are still the working directory's (SPC's GEOMETRY updates SUMFILES and LMKFILES).
    """
    from spctool.formats.landmark import read_lmk
    from spctool.formats.sumfile import read_sum
    from spctool.geometry.camera import Camera

    if not (sigma_px > 0 and math.isfinite(sigma_px)):
        raise SpcUsageError(f"--sigma-px must be a positive number, got {sigma_px}")
    weights = _weights(settings)
    notes: list[str] = []
    names = [p.strip() for p in pictures] if pictures else wd.picture_names()
    twice = sorted(n for n, c in Counter(names).items() if c > 1)
    if twice and pictures:  # one picture counted twice: its measurements doubled, its SUM written twice
        raise SpcUsageError(f"picture(s) named more than once: {', '.join(twice)}")
    if twice:
        listed = wd.pictlist_path.name
        notes.append(f"{listed} lists picture(s) more than once, each used once: {', '.join(twice)}")
        names = list(dict.fromkeys(names))
    batch_sums = None
    if from_batch is not None:
        batch_sums = Path(from_batch) / "SUMFILES"
        if not batch_sums.is_dir():
            raise SpcUsageError(f"{from_batch}: not a batch output (no SUMFILES folder)")
        done = {p.stem for p in batch_sums.glob("*.SUM")}
        if not pictures:
            missing = [n for n in names if n not in done]
            if missing:  # pictures the batch wrote no SUM for (failed, not yet run): said, not silent
                shown = ", ".join(missing[:8]) + (f", ... ({len(missing)})" if len(missing) > 8 else "")
                notes.append(f"{from_batch}: no SUM for {shown}: left out of the refinement")
            names = [n for n in names if n in done]
        tables = from_batch if tables is None else tables
    if not names:
        raise SpcUsageError(f"{wd.root}: no pictures to refine (no active PICTLIST picture, no SUMFILES/)")
    tables_dir = None
    if tables is not None:
        tables_dir = Path(tables)
        if (tables_dir / TABLES_DIR).is_dir():
            tables_dir = tables_dir / TABLES_DIR
        if not tables_dir.is_dir():
            raise SpcUsageError(f"{tables}: not a folder of register tables")
    pics, sum_paths, cams, row_sources = {}, {}, [], []
    obs_pic, obs_name, obs_pix, obs_use, obs_cov = [], [], [], [], []
    for j, name in enumerate(names):  # file reads per picture; the numerics are vectorised later
        path = wd.sum_path(name)
        src = batch_sums / path.name if batch_sums is not None else path
        if not src.exists():
            raise SpcFormatError(src, None, f"the SUM file of picture {name} (file not found)")
        pic = read_sum(src)
        guard.check_sum_header(pic, src)  # a NaN pose or a skewed CX/CY/CZ: exit 2, naming the file
        pics[name], sum_paths[name] = pic, path
        cams.append(Camera.from_picture(pic, settings))
        tpath = tables_dir / TABLE_PATTERN.format(picture=name) if tables_dir is not None else None
        if tpath is not None and tpath.exists():
            lm_names, pix, usable, cov = _table_rows(tpath, name)
        else:
            if tpath is not None:
                notes.append(
                    f"picture {name}: no register table in {tables_dir}: its SUM LANDMARKS rows used"
                )
            row_sources.append((src, pic))
            guard.check_landmark_rows(pic, src)  # one landmark on two rows would be counted twice
            lm_names = [lm.name.strip() for lm in pic.landmarks]
            pix = np.array([[lm.sample, lm.line] for lm in pic.landmarks], dtype=np.float64).reshape(-1, 2)
            usable = np.array([lm.flag.strip() != "*" for lm in pic.landmarks], dtype=bool)
            cov = None
        if cov is None:
            cov = np.broadcast_to(np.eye(2) * sigma_px**2, (len(lm_names), 2, 2))
        else:
            cov = cov + np.eye(2) * sigma_floor_px**2
        obs_pic += [j] * len(lm_names)
        obs_name += lm_names
        obs_pix.append(pix)
        obs_use.append(usable)
        obs_cov.append(np.asarray(cov))
    # landmarks measured anywhere
    lmk_names = sorted(set(obs_name))
    lmks, lmk_paths, pos, sig = {}, {}, [], []
    missing = set()
    for lname in lmk_names:  # one LMK read per landmark
        lpath = wd.lmk_path(lname)
        if not lpath.exists():
            missing.add(lname)
            continue
        lmk = read_lmk(lpath)
        lmks[lname], lmk_paths[lname] = lmk, lpath
        s = np.asarray(lmk.sigma_lmk, dtype=np.float64)
        if not np.all(np.isfinite(s) & (s > 0)):
            s = np.full(3, lmk.sigkm) if (math.isfinite(lmk.sigkm) and lmk.sigkm > 0) else np.full(3, np.nan)
        pos.append(lmk.vlm)
        sig.append(_scaled_sigma(s, weights["landmark_prior"]))
    if missing:
        notes.append(
            f"{len(missing)} landmark(s) measured but without an LMK file, their measurements left out: "
            + ", ".join(sorted(missing)[:8])
            + (" …" if len(missing) > 8 else "")
        )
    kept = [n for n in lmk_names if n not in missing]
    index = {n: i for i, n in enumerate(kept)}
    obs_pix = np.concatenate(obs_pix).reshape(-1, 2) if obs_pix else np.zeros((0, 2))
    obs_use = np.concatenate(obs_use) if obs_use else np.zeros(0, bool)
    obs_cov = np.concatenate(obs_cov).reshape(-1, 2, 2) if obs_cov else np.zeros((0, 2, 2))
    has = np.array([n in index for n in obs_name], dtype=bool)
    obs_l = np.array([index.get(n, -1) for n in obs_name], dtype=np.int64)[has]
    obs_p = np.asarray(obs_pic, dtype=np.int64)[has]
    cov = obs_cov[has]
    good = np.all(np.isfinite(cov), axis=(1, 2)) & (cov[:, 0, 0] > 0) & (np.linalg.det(cov) > 0)
    wts = np.zeros_like(cov)
    wts[good] = np.linalg.inv(cov[good]) * weights["measurements"]
    use = obs_use[has] & good
    if (~good & obs_use[has]).any():
        notes.append(
            f"{int((~good & obs_use[has]).sum())} measurement(s) without a usable covariance: not used"
        )
    ignore = {p.strip() for p in ignore_in_vlm}
    unknown = ignore - set(names)
    if unknown:
        raise SpcUsageError(
            f"--ignore-in-vlm names picture(s) not in the solve: {', '.join(sorted(unknown))}"
        )
    problem = BundleProblem(
        cameras=cams,
        picture_names=names,
        sigma_position=np.array(
            [_scaled_sigma(pics[n].sigma_vso, weights["position"]) for n in names]
        ).reshape(-1, 3),
        sigma_attitude=np.array(
            [_scaled_sigma(pics[n].sigma_ptg, weights["pointing"]) for n in names]
        ).reshape(-1, 3),
        landmark_names=kept,
        landmark_positions=np.array(pos, dtype=np.float64).reshape(-1, 3),
        landmark_sigmas=np.array(sig, dtype=np.float64).reshape(-1, 3),
        obs_picture=obs_p,
        obs_landmark=obs_l,
        obs_pixel=obs_pix[has],
        obs_weight=wts,
        obs_use=use,
        vlm_pictures=np.array([n not in ignore for n in names], dtype=bool),
    )
    return RefineInputs(
        problem,
        pics,
        sum_paths,
        lmks,
        lmk_paths,
        "tables" if tables_dir else "sum",
        notes,
        weights,
        row_sources,
    )


# ------------------------------------------------------------------------------------------------
# writing back


def updated_files(inputs: RefineInputs, result: BundleResult, wd: WorkDir) -> dict:
    """{path: new content (str for text, bytes for MAP)} of every file the refinement changes."""
    from spctool.formats.landmark import LandmarkPicture, format_lmk
    from spctool.formats.maplet import format_map, read_map
    from spctool.formats.sumfile import SumLandmark, format_sum, with_pose

    prob = inputs.problem
    out: dict = {}
    status = result.obs_status
    rms = result.landmark_rms_px()
    sig = result.landmark_sigmas
    scale = result.covariance_scale  # chi2/dof when above 1, as the reports say
    # landmarks
    # each landmark's measurements, in measurement order (one stable sort, no loop over measurements)
    order = np.argsort(prob.obs_landmark, kind="stable")
    counts = np.bincount(prob.obs_landmark, minlength=len(prob.landmark_names))
    by_lmk = np.split(order, np.cumsum(counts)[:-1])
    for i, name in enumerate(prob.landmark_names):
        lmk = inputs.landmarks[name]
        changes = {}
        if result.landmark_status[i] == "ok":
            changes["vlm"] = result.landmark_positions[i].copy()
            changes["sigma_lmk"] = sig[i] * math.sqrt(scale)
            if math.isfinite(rms[i]):
                changes["rmslmk"] = float(rms[i])
        rows = list(lmk.pictures)
        where = {r.name.strip(): n for n, r in enumerate(rows)}
        for k in by_lmk[i]:
            pname = prob.picture_names[prob.obs_picture[k]]
            flag = "" if status[k] in ("ok", "undetermined", "ignored-in-vlm") else "*"
            row = LandmarkPicture(pname, float(prob.obs_pixel[k, 0]), float(prob.obs_pixel[k, 1]), flag)
            if pname in where:
                rows[where[pname]] = row
            else:
                where[pname] = len(rows)
                rows.append(row)
        changes["pictures"] = rows
        new = replace(lmk, **changes)
        text = format_lmk(new)
        out[inputs.lmk_paths[name]] = text
        if "vlm" in changes:
            mpath = wd.map_path(name)
            if mpath.exists():
                m = read_map(mpath)
                m.v = np.asarray(changes["vlm"], dtype=np.float64)
                out[mpath] = format_map(m)
    # pictures
    outlier_of: dict[str, set] = {}
    for k, s in enumerate(status):
        if s == "outlier":
            pname = prob.picture_names[prob.obs_picture[k]]
            outlier_of.setdefault(pname, set()).add(prob.landmark_names[prob.obs_landmark[k]])
    psig = result.pose_sigmas * math.sqrt(scale)
    for j, name in enumerate(prob.picture_names):
        pic = inputs.pictures[name]
        rot = result.rotations[j]
        new = with_pose(pic, -result.positions[j], rot, psig[j, :3], psig[j, 3:])
        bad = outlier_of.get(name, set())
        if bad:
            rows = [
                SumLandmark(lm.name, lm.sample, lm.line, "*") if lm.name.strip() in bad else lm
                for lm in new.landmarks
            ]
            new = replace(new, landmarks=rows)
        out[inputs.sum_paths[name]] = format_sum(new)
    return out


def write_back(files: dict, *, backup: bool = True) -> list[Path]:
    """Write every file that changes atomically (temporary file + rename: a link or hard link at the path
    is replaced, never written through), a replaced one keeping its ``.bak`` unless ``backup`` is false;
    returns the paths written."""
    written = []
    for path, content in files.items():  # one atomic write per file
        data = content.encode("latin-1") if isinstance(content, str) else content
        try:
            old = Path(path).read_bytes()
        except OSError:
            old = None
        if old == data:
            continue
        atomic.write_bytes(path, data, overwrite=True, backup=backup)
        written.append(Path(path))
    return written


# ------------------------------------------------------------------------------------------------
# reports


def residuals_table(result: BundleResult, problem: BundleProblem):
    """RESIDUALS-style: one row per measurement (landmark, picture, measured pixel, residuals before and
    after, normalised residual, status)."""
    from spctool.formats.table import LandmarkTable

    cols = {
        "name": [result.landmark_names[i] for i in problem.obs_landmark],
        "picture": [result.picture_names[j] for j in problem.obs_picture],
        "sample": problem.obs_pixel[:, 0],
        "line": problem.obs_pixel[:, 1],
        "residual_sample_before": result.residual_before[:, 0],
        "residual_line_before": result.residual_before[:, 1],
        "residual_sample_after": result.residual_after[:, 0],
        "residual_line_after": result.residual_after[:, 1],
        "rho": result.rho_after,
        "status": list(result.obs_status),
    }
    table = LandmarkTable(cols, picture="", command="geometry", meta={"kind": "residuals"})
    table.comments.append(
        "post-fit residuals per landmark and picture: measured - predicted (px); rho = normalised residual; "
        "status ok / outlier (flagged here) / flagged (* on input) / ignored-in-vlm / undetermined"
    )
    return table


def summary_table(result: BundleResult, problem: BundleProblem):
    """One row per landmark: VLM before/after, correction (m), 1σ (m), pictures used, rms (px), status.
    The 1σ of a refined landmark is its SIGMA_LMK as written (scaled by chi2/dof when above 1,
    :attr:`BundleResult.covariance_scale`); an undetermined one's is its prior's."""
    from spctool.formats.table import LandmarkTable

    n = len(result.landmark_names)
    used = np.array([s in ("ok", "undetermined") for s in result.obs_status])
    npic = np.bincount(problem.obs_landmark[used], minlength=n)
    d = (result.landmark_positions - result.landmark_positions0) * 1000.0
    ok = np.array([s == "ok" for s in result.landmark_status], dtype=bool)
    sig = result.landmark_sigmas * 1000.0
    sig[ok] *= math.sqrt(result.covariance_scale)
    cols = {
        "name": list(result.landmark_names),
        "vlm_x": result.landmark_positions[:, 0],
        "vlm_y": result.landmark_positions[:, 1],
        "vlm_z": result.landmark_positions[:, 2],
        "dx_m": d[:, 0],
        "dy_m": d[:, 1],
        "dz_m": d[:, 2],
        "sigma_x_m": sig[:, 0],
        "sigma_y_m": sig[:, 1],
        "sigma_z_m": sig[:, 2],
        "pictures": npic,
        "parallax_deg": result.landmark_parallax_deg,
        "rms_px": result.landmark_rms_px(),
        "status": list(result.landmark_status),
    }
    return LandmarkTable(cols, picture="", command="geometry", meta={"kind": "landmarks"})


def lmkvecs_text(result: BundleResult, landmarks: dict) -> str:
    """LMKVECS.TXT: VLM(3) (km), name, HFLAG per landmark (spc-formats.md §7.6), ``3F16.8,2X,A6,2X,A1``."""
    lines = []
    for i, name in enumerate(result.landmark_names):
        v = result.landmark_positions[i]
        h = getattr(landmarks.get(name), "hflag", "F") or "F"
        lines.append("".join(f"{x:16.8f}" for x in v) + f"  {name:<6s}  {h}")
    return "\n".join(lines) + ("\n" if lines else "")


def formal_summary(result: BundleResult) -> dict:
    """Formal uncertainty in the spirit of get80: the 1σ position error (m, root of the covariance's trace)
    of the best 80 % of the determined landmarks, with its median and maximum; the covariance scaled as
    SIGMA_LMK is written (``covariance_scale``: chi2/dof when above 1)."""
    ok = np.array([s == "ok" for s in result.landmark_status])
    scale = result.covariance_scale
    tr = (
        np.sqrt(np.trace(result.landmark_covariance[ok], axis1=1, axis2=2) * scale) * 1000.0
        if ok.any()
        else np.zeros(0)
    )
    tr = np.sort(tr[np.isfinite(tr)])
    k = int(math.ceil(0.8 * tr.size))
    best = tr[:k]
    return {
        "covariance_scale": scale,
        "landmarks": int(ok.sum()),
        "best80_count": int(best.size),
        "best80_rms_m": float(np.sqrt(np.mean(best**2))) if best.size else math.nan,
        "best80_max_m": float(best.max()) if best.size else math.nan,
        "median_m": float(np.median(tr)) if tr.size else math.nan,
    }
