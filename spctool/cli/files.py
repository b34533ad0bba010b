"""``info``, ``validate`` and ``convert``: inspect, check and convert SPC files and photos."""

from __future__ import annotations

import dataclasses
import io
import json
import math
from pathlib import Path

import click
import numpy as np

from spctool import __version__
from spctool.cli.common import Context, emit, pass_context
from spctool.errors import SpcFormatError, SpcUsageError
from spctool.formats import atomic, guard
from spctool.formats.detect import PHOTO_KINDS, detect_kind

# ------------------------------------------------------------------------------------------------
# reading any kind


def read_any(path, kind: str, *, npx=None, nln=None, byte_order="auto", flip_rows=False):
    """Read ``path`` as ``kind`` with the matching formats reader."""
    if kind == "sum":
        from spctool.formats.sumfile import read_sum

        return read_sum(path)
    if kind == "nom":
        from spctool.formats.nominal import read_nom

        return read_nom(path)
    if kind == "lmk":
        from spctool.formats.landmark import read_lmk

        return read_lmk(path)
    if kind == "map":
        from spctool.formats.maplet import read_map

        return read_map(path)
    if kind == "icq":
        from spctool.formats.icq import read_icq

        return read_icq(path)
    if kind == "obj":
        from spctool.formats.mesh import read_obj

        return read_obj(path)
    if kind == "vtk":
        from spctool.formats.mesh import read_vtk

        return read_vtk(path)
    if kind == "lithos":
        from spctool.formats.lithos import read_lithos

        return read_lithos(path)
    if kind == "pictlist":
        from spctool.formats.lists import read_pictlist

        return read_pictlist(path)
    if kind == "lmrklist":
        from spctool.formats.lists import read_lmrklist

        return read_lmrklist(path)
    if kind == "lmrklistx":
        from spctool.formats.lists import read_lmrklistx

        return read_lmrklistx(path)
    if kind == "table":
        from spctool.formats.table import read_table

        return read_table(path)
    if kind in PHOTO_KINDS:
        from spctool.formats.photo import read_photo

        if kind == "dat" and (npx is None or nln is None):
            raise SpcUsageError(f"{path}: a .DAT photo needs its size: give --sum FILE or --npx/--nln")
        return read_photo(path, npx=npx, nln=nln, byte_order=byte_order, flip_rows=flip_rows)
    raise SpcUsageError(f"{path}: cannot read files of kind {kind!r}")


def _dat_size(sum_path, npx, nln):
    if sum_path:
        from spctool.formats.sumfile import read_sum

        pic = read_sum(sum_path)
        return pic.npx, pic.nln
    return npx, nln


# ------------------------------------------------------------------------------------------------
# JSON view of any dataclass


def jsonable(obj, *, arrays: bool = False, limit: int = 64):
    """Dataclasses -> dicts (private ``_fields`` skipped); big arrays summarised unless ``arrays``."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        out = {}
        for f in dataclasses.fields(obj):
            if f.name.startswith("_"):
                continue
            out[f.name] = jsonable(getattr(obj, f.name), arrays=arrays, limit=limit)
        return out
    if isinstance(obj, np.ndarray):
        if obj.size > limit and not arrays:
            finite = obj[np.isfinite(obj)] if obj.dtype.kind == "f" else obj
            summary = {"shape": list(obj.shape), "dtype": str(obj.dtype)}
            if obj.dtype.kind in "fiub" and finite.size:
                summary.update(min=float(finite.min()), max=float(finite.max()), mean=float(finite.mean()))
            return summary
        return jsonable(obj.tolist(), arrays=arrays, limit=limit)
    if isinstance(obj, dict):
        return {str(k): jsonable(v, arrays=arrays, limit=limit) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v, arrays=arrays, limit=limit) for v in obj]
    if isinstance(obj, (np.floating, float)):
        v = float(obj)
        return v if math.isfinite(v) else None
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (np.bool_,)):
        return bool(obj)
    if isinstance(obj, Path):
        return str(obj)
    return obj


# ------------------------------------------------------------------------------------------------
# human summaries


def _vec(v, fmt="{:.6g}"):
    return "(" + ", ".join(fmt.format(float(x)) for x in np.ravel(v)) + ")"


def summarize(kind: str, obj) -> list[str]:
    if kind == "sum":
        lines = [
            f"picture {obj.name}  {obj.utc}",
            f"detector {obj.npx} x {obj.nln} px, THRSH {obj.thrsh[0]:g}..{obj.thrsh[1]:g}",
            f"MMFL {obj.mmfl:g} mm, CTR {_vec(obj.ctr)}, K {_vec(obj.kmatrix)} px/mm",
            f"SCOBJ {_vec(obj.scobj)} km (range {np.linalg.norm(obj.scobj):.6g} km)",
            f"SZ {_vec(obj.sz)}",
            f"DISTORTION {_vec(obj.distortion) if obj.distortion is not None else 'absent'}",
            f"SIGMA_VSO {_vec(obj.sigma_vso)} km, SIGMA_PTG {_vec(obj.sigma_ptg)} rad",
            f"{len(obj.landmarks)} landmarks, {len(obj.limb_fits)} limb fits",
        ]
        lines += [
            f"  {lm.name}  {lm.sample:10.2f} {lm.line:10.2f} {lm.flag}".rstrip() for lm in obj.landmarks
        ]
        return lines
    if kind == "nom":
        return [
            f"nominal {obj.name}",
            f"SCOBJ {_vec(obj.scobj)} km",
            f"SIGMA_VSO {_vec(obj.sigma_vso)} km ({obj.frame_tag})",
            f"SIGMA_PTG {_vec(obj.sigma_ptg)} rad",
        ]
    if kind == "lmk":
        lines = [
            f"landmark {obj.name} (HFLAG {obj.hflag}), QSZ {obj.qsz} ({2 * obj.qsz + 1}^2 cells), "
            f"SCALE {obj.scale:g} km",
            f"VLM {_vec(obj.vlm)} km (radius {np.linalg.norm(obj.vlm):.6g} km)",
            f"UX {_vec(obj.ux)}  UY {_vec(obj.uy)}  UZ {_vec(obj.uz)}",
            f"SIGKM {obj.sigkm:g}, RMSLMK {obj.rmslmk:g}, SIGMA_LMK {_vec(obj.sigma_lmk)}",
            f"{len(obj.pictures)} pictures, {len(obj.overlaps)} map overlaps, {len(obj.limb_fits)} limb fits",
        ]
        lines += [f"  {p.name:<12} {p.sample:10.2f} {p.line:10.2f} {p.flag}".rstrip() for p in obj.pictures]
        return lines
    if kind == "map":
        n = obj.heights.shape[0]
        valid = obj.valid
        h = obj.heights[valid]
        return [
            f"maplet {obj.name or '-'}: {n} x {n} cells (QSZ {obj.qsz}), SCALE {obj.scale:g} km "
            f"({n * obj.scale:g} km across)",
            f"V {_vec(obj.v)} km",
            f"UX {_vec(obj.ux)}  UY {_vec(obj.uy)}  UZ {_vec(obj.uz)}",
            f"HSCALE {obj.hscale:g}; {int(valid.sum())} valid cells, {int((~valid).sum())} missing",
            (
                f"heights {h.min():.4g} .. {h.max():.4g} cells; albedo {obj.albedo[valid].min():.2f} .. "
                f"{obj.albedo[valid].max():.2f}"
            )
            if h.size
            else "no valid cells",
        ]
    if kind == "icq":
        v = obj.vertices.reshape(-1, 3)
        return [
            f"ICQ shape q={obj.q}: {obj.vertex_count} vertices, {6 * obj.q**2} cells"
            + (" with albedo" if obj.albedo is not None else ""),
            f"extent x {v[:, 0].min():.6g}..{v[:, 0].max():.6g}, y {v[:, 1].min():.6g}..{v[:, 1].max():.6g}, "
            f"z {v[:, 2].min():.6g}..{v[:, 2].max():.6g} km",
        ]
    if kind in ("obj", "vtk"):
        v = obj.vertices
        return [
            f"triangle mesh: {len(v)} vertices, {len(obj.faces)} triangles",
            f"extent x {v[:, 0].min():.6g}..{v[:, 0].max():.6g}, y {v[:, 1].min():.6g}..{v[:, 1].max():.6g}, "
            f"z {v[:, 2].min():.6g}..{v[:, 2].max():.6g} km",
        ]
    if kind == "lithos":
        lines = [f"INIT_LITHOS: {len(obj.keys)} keys, {len(obj.distortions)} DISTORT= models"]
        lines += [f"  {k} = {v}" for k, v in obj.keys.items()]
        lines += [
            f"  DISTORT '{d.template}' {d.model} J={d.order}: {_vec(d.coefficients)}" for d in obj.distortions
        ]
        return lines
    if kind == "pictlist":
        return [f"picture list: {len(obj.entries)} pictures, {len(obj.active_names)} in use"]
    if kind == "lmrklist":
        return [f"landmark list: {len(obj.active_names)} active landmarks"]
    if kind == "lmrklistx":
        return [f"landmark list X: {len(obj.entries)} landmarks"]
    if kind == "table":
        return [f"landmark table: {len(obj)} rows, columns {', '.join(obj.columns)}"]
    if kind in PHOTO_KINDS:
        d = obj.data
        return [
            f"photo {obj.npx} x {obj.nln} px (sample x line), {d.dtype} ({obj.bits}-bit)",
            f"DN {d.min()} .. {d.max()}, mean {d.mean():.6g}, zero (missing) pixels {int((d == 0).sum())}",
        ]
    return [repr(obj)]


# ------------------------------------------------------------------------------------------------
# validation


def _stage_ready(obj, out: list[str]) -> None:
    """What the stages require of a landmark or maplet (a file validate passes never crashes one)."""
    from spctool.formats.guard import landmark_geometry_problem

    problem = landmark_geometry_problem(obj)
    if problem is not None and not out:
        out.append(f"expected {problem} (the stages refuse this landmark)")


def problems_of(kind: str, obj) -> list[str]:
    """Semantic problems beyond parsing (each one line)."""
    out: list[str] = []

    def check_frame(label, rows, det_sign=1.0):
        m = np.asarray(rows, float)
        err = np.abs(m @ m.T - np.eye(3)).max()
        if err > 1e-5:
            out.append(f"{label} is not orthonormal (max |R R^T - I| = {err:.2e})")
        elif abs(np.linalg.det(m) - det_sign) > 1e-5:
            out.append(f"{label} is not right-handed (det {np.linalg.det(m):+.6f})")

    if kind == "sum":
        check_frame("CX/CY/CZ", obj.rotation)
        from spctool.formats.guard import MAX_INPUT_BYTES

        if float(obj.npx) * float(obj.nln) * 8 > MAX_INPUT_BYTES:
            out.append(f"NPX x NLN = {obj.npx} x {obj.nln} is too large a photo")
        if obj.npx <= 0 or obj.nln <= 0:
            out.append(f"NPX, NLN must be positive, found {obj.npx}, {obj.nln}")
        if obj.thrsh[0] > obj.thrsh[1]:
            out.append(f"THRSH lower {obj.thrsh[0]:g} exceeds upper {obj.thrsh[1]:g}")
        if obj.mmfl <= 0:
            out.append(f"MMFL must be positive, found {obj.mmfl:g}")
        if abs(np.linalg.det(obj.kmatrix[:, :2])) < 1e-12:
            out.append("K-MATRIX is singular")
        if abs(np.linalg.norm(obj.sz) - 1) > 1e-3:
            out.append(f"SZ is not a unit vector (norm {np.linalg.norm(obj.sz):.6f})")
        from spctool.formats.guard import duplicate_landmarks

        dups = duplicate_landmarks(obj)
        if dups:
            shown = ", ".join(dups[:10]) + (f", ... ({len(dups)} names)" if len(dups) > 10 else "")
            out.append(f"duplicate landmark rows: {shown}")
    elif kind == "lmk":
        check_frame("UX/UY/UZ", np.vstack([obj.ux, obj.uy, obj.uz]))
        if obj.scale <= 0:
            out.append(f"SCALE must be positive, found {obj.scale:g}")
        if obj.qsz <= 0:
            out.append(f"QSZ must be positive, found {obj.qsz}")
        _stage_ready(obj, out)
    elif kind == "map":
        check_frame("UX/UY/UZ", np.vstack([obj.ux, obj.uy, obj.uz]))
        if not obj.scale > 0:
            out.append(f"SCALE must be positive, found {obj.scale:g}")
        _stage_ready(obj, out)
        if not obj.valid.any():
            out.append("no valid cell (every albedo byte is 0)")
    elif kind == "icq":
        from spctool.formats.icq import seam_identity_pairs

        a, b = seam_identity_pairs(obj.q)
        flat = obj.flat_vertices()
        bad = np.any(flat[a] != flat[b], axis=1)
        if bad.any():
            out.append(
                f"{int(bad.sum())} of {len(a)} seam vertices differ from their duplicates "
                "(not an exact ICQ dump)"
            )
    elif kind in ("obj", "vtk"):
        if len(obj.faces) and (obj.faces.min() < 0 or obj.faces.max() >= len(obj.vertices)):
            out.append("a face refers to a vertex that does not exist")
    return out


def spc_warnings(obj) -> list[tuple[int | None, str]]:
    """(line, text) where SPC's Fortran reads the file differently from a careless reader (issue #14).

    Not errors: SPC accepts the file.  An unknown DISTORT= model is one (SPC uses the plain pinhole).
    """
    found = getattr(obj, "warnings", None)
    if found is None:
        found = getattr(obj, "__dict__", {}).get("_spc_warnings")
    if found is None:
        src = getattr(obj, "_source", None)
        found = getattr(src, "warnings", None)
    return list(found or [])


# ------------------------------------------------------------------------------------------------
# commands


@click.command("info")
@click.argument("files", nargs=-1, required=True, type=click.Path(dir_okay=False))
@click.option("--json", "as_json", is_flag=True, help="Every field as one JSON document.")
@click.option("--arrays", is_flag=True, help="With --json, write large arrays in full (heights, pixels).")
@click.option("--npx", type=int, help="Width of a .DAT photo (else taken from --sum).")
@click.option("--nln", type=int, help="Height of a .DAT photo (else taken from --sum).")
@click.option(
    "--sum", "sum_path", type=click.Path(dir_okay=False), help="SUM file giving a .DAT photo's size."
)
@pass_context
def info_cmd(ctx: Context, files, as_json, arrays, npx, nln, sum_path):
    """Describe SPC files and photos; the type is detected from the content.

    --json writes {"command", "spctool_version", "files": [one object per FILE]}; with one FILE its
    fields are also at the top level.

    Example:

    \b
      spctool info demo/SUMFILES/P000000001A1.SUM demo/LMKFILES/B01980.LMK
      spctool info --json demo/MAPFILES/B01980.MAP | jq .scale
    """
    npx, nln = _dat_size(sum_path, npx, nln)
    docs = []
    for f in files:
        kind = detect_kind(f)
        obj = read_any(f, kind, npx=npx, nln=nln)
        if as_json:
            doc = {"file": str(f), "kind": kind}
            body = obj.to_json_dict() if kind == "table" else jsonable(obj, arrays=arrays)
            doc.update(body if isinstance(body, dict) else {"value": body})
            docs.append(doc)
        else:
            click.echo(f"{f}: {kind}")
            for line in summarize(kind, obj):
                click.echo("  " + line)
    if as_json:
        payload = {"command": "info", "spctool_version": __version__, "files": docs}
        if len(docs) == 1:  # one FILE: its fields at the top level too (jq .scale)
            payload = {**{k: v for k, v in docs[0].items() if k not in payload}, **payload}
        emit(json.dumps(payload, indent=2, allow_nan=False) + "\n")


@click.command("validate")
@click.argument("files", nargs=-1, required=True, type=click.Path(dir_okay=False))
@click.option("--json", "as_json", is_flag=True, help="Report as JSON.")
@click.option("--npx", type=int, help="Width of a .DAT photo.")
@click.option("--nln", type=int, help="Height of a .DAT photo.")
@click.option(
    "--sum", "sum_path", type=click.Path(dir_okay=False), help="SUM file giving a .DAT photo's size."
)
@pass_context
def validate_cmd(ctx: Context, files, as_json, npx, nln, sum_path):
    """Check SPC files and photos: exit 0 when all are valid, 2 when any is not.

    Every problem is listed, one line each (FILE:LINE: problem); the parse is followed by
    semantic checks (orthonormal frames, thresholds, ICQ seams, ...).  Lines that SPC's Fortran
    reads differently from a careless reader (text past column 80 of a formatted record, an
    unknown DISTORT= model, a DISTORTION tag off columns 64-73 ...) are reported as
    "FILE:LINE: warning: ..." and do not change the exit code.

    Example:

    \b
      spctool validate demo/SUMFILES/*.SUM demo/LMKFILES/*.LMK demo/MAPFILES/*.MAP
    """
    npx, nln = _dat_size(sum_path, npx, nln)
    report = []
    bad = 0
    for f in files:
        entry = {"file": str(f), "kind": None, "valid": True, "problems": []}
        try:
            kind = detect_kind(f)
            entry["kind"] = kind
            obj = read_any(f, kind, npx=npx, nln=nln)
            entry["problems"] = [f"{f}: {p}" for p in problems_of(kind, obj)]
            if kind in guard.FINITE_KEYS:  # read as SPC reads it, but no stage could use a NaN pose
                try:
                    guard.check_finite_header(obj, f, kind)
                except SpcFormatError as exc:
                    entry["problems"].insert(0, str(exc))
            entry["warnings"] = [
                f"{f}:{line}: warning: {text}" if line else f"{f}: warning: {text}"
                for line, text in spc_warnings(obj)
            ]
        except SpcFormatError as exc:
            entry["problems"] = [str(exc)]
        except SpcUsageError as exc:
            entry["problems"] = [str(exc)]
        entry["valid"] = not entry["problems"]
        bad += not entry["valid"]
        report.append(entry)
        if not as_json:
            if entry["valid"]:
                click.echo(f"{f}: valid {entry['kind']}")
            for p in entry.get("warnings", []) + entry["problems"]:
                click.echo(p, err=True)
    if as_json:
        emit(
            json.dumps({"command": "validate", "spctool_version": __version__, "files": report}, indent=2)
            + "\n"
        )
    ctx_exit = 2 if bad else 0
    if ctx_exit:
        raise click.exceptions.Exit(ctx_exit)


_PHOTO_EXT = {".fits": "fits", ".fit": "fits", ".pgm": "pgm", ".png": "png", ".dat": "dat"}


def _out_kind(path: Path) -> str:
    ext = path.suffix.lower()
    if ext in _PHOTO_EXT:
        return _PHOTO_EXT[ext]
    if ext == ".npz":
        return "npz"
    if ext == ".obj":
        return "obj"
    if ext == ".vtk":
        return "vtk"
    if ext in (".icq",) or path.name.upper().startswith("SHAPE"):
        return "icq"
    if ext == ".map":
        return "map"
    if ext == ".sum":
        return "sum"
    if ext == ".nom":
        return "nom"
    if ext == ".lmk":
        return "lmk"
    return ""


def _map_images(maplet, out: Path, kind: str, overwrite: bool, backup: bool) -> list[Path]:
    """MAP -> height and albedo images (FITS: one file, two HDUs; PGM/PNG: OUT and OUT's .albedo sibling)."""
    from spctool.formats.photo import Photo, write_photo

    valid = maplet.valid
    if kind == "fits":
        from astropy.io import fits

        hdr = fits.Header()
        hdr["EXTNAME"] = "HEIGHT"
        hdr["BUNIT"] = "cell"
        hdr["COMMENT"] = "heights in units of SCALE; axis 0 (rows) = J along UX, axis 1 = I along UY"
        hdr["MAPNAME"] = maplet.name or ""
        hdr["SCALE"] = (float(maplet.scale), "km per cell")
        hdr["QSZ"] = int(maplet.qsz)
        for label, vec in (("V", maplet.v), ("UX", maplet.ux), ("UY", maplet.uy), ("UZ", maplet.uz)):
            for i, axis in enumerate("XYZ"):
                hdr[f"{label}{axis}"] = float(vec[i])
        heights = np.where(valid, maplet.heights, np.nan).astype(np.float64)
        albedo = np.where(valid, maplet.albedo, np.nan).astype(np.float64)
        hdul = fits.HDUList(
            [
                fits.PrimaryHDU(heights, header=hdr),
                fits.ImageHDU(albedo, name="ALBEDO"),
                fits.ImageHDU(valid.astype(np.uint8), name="VALID"),
            ]
        )
        buf = io.BytesIO()
        hdul.writeto(buf)
        atomic.write_bytes(out, buf.getvalue(), overwrite=overwrite, backup=backup)
        return [out]
    if kind in ("pgm", "png"):
        h = maplet.heights[valid]
        lo, hi = (float(h.min()), float(h.max())) if h.size else (0.0, 1.0)
        span = hi - lo if hi > lo else 1.0
        img = np.zeros(maplet.heights.shape, np.uint16)
        img[valid] = 1 + np.round((maplet.heights[valid] - lo) / span * 65534).astype(np.uint16)
        alb = np.zeros(maplet.heights.shape, np.uint8)
        alb[valid] = np.clip(np.round(maplet.albedo[valid] * 100), 1, 255).astype(np.uint8)
        second = out.with_name(out.stem + ".albedo" + out.suffix)
        write_photo(out, Photo(data=img, name=maplet.name or "", bits=16), overwrite=overwrite, backup=backup)
        write_photo(
            second, Photo(data=alb, name=maplet.name or "", bits=8), overwrite=overwrite, backup=backup
        )
        return [out, second]
    if kind == "npz":
        buf = io.BytesIO()
        np.savez(
            buf,
            heights=maplet.heights,
            albedo=maplet.albedo,
            valid=valid,
            scale=maplet.scale,
            qsz=maplet.qsz,
            v=maplet.v,
            ux=maplet.ux,
            uy=maplet.uy,
            uz=maplet.uz,
            hscale=maplet.hscale,
        )
        atomic.write_bytes(out, buf.getvalue(), overwrite=overwrite, backup=backup)
        return [out]
    raise SpcUsageError(f"{out}: a maplet converts to .fits, .pgm, .png, .npz or .MAP")


@click.command("convert")
@click.argument("src", type=click.Path(dir_okay=False, exists=True))
@click.argument("dst", type=click.Path(dir_okay=False))
@click.option(
    "--flip-rows", is_flag=True, help="Reverse the row order of a photo (bottom-up storage -> SPC order)."
)
@click.option("--npx", type=int, help="Width of a .DAT input photo.")
@click.option("--nln", type=int, help="Height of a .DAT input photo.")
@click.option(
    "--sum", "sum_path", type=click.Path(dir_okay=False), help="SUM file giving a .DAT photo's size."
)
@click.option(
    "--byte-order",
    type=click.Choice(["auto", "big", "little"]),
    default="auto",
    show_default=True,
    help="Byte order of a 16-bit .DAT input (auto: SPC's Laplacian test).",
)
@click.option(
    "--icq-style",
    type=click.Choice(["spc", "exact"]),
    default="spc",
    show_default=True,
    help="ICQ output numbers: SPC's 3F12.5 or full precision.",
)
@click.option("--force", is_flag=True, help="Overwrite DST if it exists.")
@click.option("--backup", is_flag=True, help="Keep DST.bak when overwriting (always done; kept for scripts).")
@pass_context
def convert_cmd(ctx: Context, src, dst, flip_rows, npx, nln, sum_path, byte_order, icq_style, force, backup):
    """Convert SPC files and photos.

    Same format to same format is a clean rewrite (byte-identical when nothing changed);
    MAP -> FITS/PGM/PNG/NPZ of height and albedo; ICQ <-> OBJ (an OBJ whose vertices are
    in ICQ order becomes a true ICQ); photos between DAT/FITS/PGM/PNG, 16-bit kept 16-bit.

    Example:

    \b
      spctool convert demo/SHAPEFILES/SHAPE.TXT shape.obj
      spctool convert shape.obj SHAPE.TXT
      spctool convert --sum demo/SUMFILES/P000000001A1.SUM demo/IMAGEFILES/P000000001A1.DAT P1.fits
      spctool convert --flip-rows P1.fits upside_down.png
    """
    src_p, dst_p = Path(src), Path(dst)
    if src_p.resolve() == dst_p.resolve() and not force:
        raise SpcUsageError(f"{dst}: refusing to overwrite the input (use --force: it is kept as .bak)")
    if dst_p.exists() and not force:
        raise SpcUsageError(f"{dst}: exists already (use --force to overwrite)")
    npx, nln = _dat_size(sum_path, npx, nln)
    kind = detect_kind(src_p)
    obj = read_any(src_p, kind, npx=npx, nln=nln, byte_order=byte_order, flip_rows=flip_rows)
    out_kind = _out_kind(dst_p) or kind
    written: list[Path] = [dst_p]
    kw = dict(overwrite=True, backup=True)  # a replaced DST is always kept as DST.bak (--backup: the same)
    if kind in PHOTO_KINDS:
        if out_kind not in PHOTO_KINDS:
            raise SpcUsageError(f"{dst}: a photo converts to .DAT, .fits, .pgm or .png")
        from spctool.formats.photo import write_photo

        write_photo(dst_p, obj, fmt=out_kind, **kw)
    elif kind == "map":
        if out_kind == "map":
            from spctool.formats.maplet import write_map

            write_map(dst_p, obj, **kw)
        else:
            written = _map_images(obj, dst_p, out_kind, True, True)
    elif kind in ("icq", "obj", "vtk"):
        if out_kind in ("", "icq", kind) and dst_p.suffix.lower() in (".txt", ".icq"):
            out_kind = "icq"  # SPC keeps shapes as SHAPEFILES/*.TXT
        from spctool.formats import icq as icqmod
        from spctool.formats import mesh as meshmod
        from spctool.formats.icq_mesh import icq_to_mesh, mesh_to_icq

        if out_kind == "icq":
            shape = obj if kind == "icq" else mesh_to_icq(obj)
            icqmod.write_icq(dst_p, shape, style=icq_style, **kw)
        elif out_kind in ("obj", "vtk"):
            mesh = icq_to_mesh(obj) if kind == "icq" else obj
            (meshmod.write_obj if out_kind == "obj" else meshmod.write_vtk)(dst_p, mesh, **kw)
        else:
            raise SpcUsageError(f"{dst}: a shape converts to ICQ (SHAPE*.TXT or .ICQ), .obj or .vtk")
    elif kind in ("sum", "nom", "lmk", "lithos", "pictlist", "lmrklist", "lmrklistx"):
        if out_kind and out_kind != kind:
            raise SpcUsageError(f"{dst}: a {kind.upper()} file converts only to its own format")
        _rewrite_text(kind, obj, dst_p, **kw)
    else:
        raise SpcUsageError(f"{src}: {kind} files cannot be converted")
    for p in written:
        ctx.info(f"wrote {p}")


def _rewrite_text(kind, obj, dst, **kw):
    if kind == "sum":
        from spctool.formats.sumfile import write_sum as w
    elif kind == "nom":
        from spctool.formats.nominal import write_nom as w
    elif kind == "lmk":
        from spctool.formats.landmark import write_lmk as w
    elif kind == "lithos":
        from spctool.formats.lithos import write_lithos as w
    elif kind == "pictlist":
        from spctool.formats.lists import write_pictlist as w
    elif kind == "lmrklist":
        from spctool.formats.lists import write_lmrklist as w
    else:
        from spctool.formats.lists import write_lmrklistx as w
    w(dst, obj, **kw)


def register(cli):
    cli.add_command(info_cmd)
    cli.add_command(validate_cmd)
    cli.add_command(convert_cmd)
