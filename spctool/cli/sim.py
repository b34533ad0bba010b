"""Synthetic worlds on the command line: ``simulate``, ``make-maplets`` and ``render``.

* ``simulate SPEC.toml OUTDIR`` — :func:`spctool.sim.simulate.simulate` (a whole SPC working directory
  with TRUTH.json);
* ``make-maplets`` — :func:`spctool.sim.maplets.make_maplets` (SPC's GET_HEIGHTS projection of the
  working directory's shape onto maplet planes, spc-algorithms.md §2.2);
* ``render PIC`` — :func:`spctool.stages.render.render` of the working directory's shape and maplets at
  the SUM pose, through :func:`spctool.sim.simulate.expose`.

The ``demo`` command (lead's) registers here too; its data live in :mod:`spctool.sim.demo`.
"""

from __future__ import annotations

import math
from pathlib import Path

import click
import numpy as np

from spctool.cli import options
from spctool.cli.common import Context, emit, emit_table, load_picture, pass_context, progress
from spctool.errors import SpcUsageError


def _spec_help() -> str:
    from spctool.sim.spec_keys import spec_help

    return spec_help(96)


# ------------------------------------------------------------------------------------------------
# simulate
# ------------------------------------------------------------------------------------------------

_SIMULATE_HELP = """Build a synthetic SPC working directory OUTDIR from SPEC (TOML), with its truth.

The world: an ICQ shape (ellipsoid or [body] shape) carrying power-law craters, boulders, fractal
roughness and albedo; landmarks with maplets derived (smoothed, down-sampled) from truth patches
truth_factor times finer (Shoemaker et al. 2016: 3 mm truth under 1 cm maplets); photos ray-traced with
cast shadows from the truth, through the SPC camera with its DISTORT= model, with detector noise; SUM
and NOM files holding a perturbed a-priori pose; INIT_LITHOS.TXT, PICTLIST.TXT, LMRKLIST.TXT and
TRUTH.json (true poses and the true pixel of every landmark in every picture). Every random draw comes
from the SPEC seed: the same SPEC gives the same bytes.

Prints one row per landmark and picture.  Columns: name (landmark), picture, true_sample and
true_line (the true pixel), emission, incidence and phase (degrees), status (ok, outside the photo,
occluded by the terrain, shadowed: in cast shadow).

Example:

\b
  spctool simulate --example > world.toml
  spctool simulate world.toml WORLD
  spctool -C WORLD lithos-select P000000001A1

SPEC keys (every key is optional):

\b
"""


@click.command("simulate", help=_SIMULATE_HELP + _spec_help())
@click.argument("spec", required=False, type=click.Path(dir_okay=False))
@click.argument("outdir", required=False, type=click.Path(file_okay=False))
@click.option("--overwrite", is_flag=True, help="Write into a non-empty OUTDIR (replacing same-named files).")
@click.option("--seed", type=int, default=None, help="Override the SPEC's seed.")
@click.option("--example", is_flag=True, help="Print a SPEC with every key at its default and exit.")
@click.option(
    "--max-memory",
    "max_memory",
    default=None,
    metavar="SIZE",
    help="Refuse a world whose estimated memory exceeds SIZE (bytes, or with K, M, G, T), checked "
    "from the SPEC before anything is allocated.  [default: half the physical memory]",
)
@options.json_option
@options.output_option
@pass_context
def simulate_cmd(ctx: Context, spec, outdir, overwrite, seed, example, max_memory, as_json, output):
    from spctool.sim.simulate import simulate
    from spctool.sim.spec import load_spec, parse_spec

    if example:
        emit(example_spec(), output)
        return
    if not spec or not outdir:
        raise SpcUsageError("simulate needs SPEC and OUTDIR (or --example)")
    sp = load_spec(spec)
    if seed is not None:
        data = sp.to_dict()
        data["seed"] = int(seed)
        sp = parse_spec(data, base=sp.base, where=str(spec))
    limit = _parse_size(max_memory) if max_memory is not None else None
    # the simulator names each step as it starts: global shape, landmarks, truth patches and maplets,
    # one render per picture, truth
    with progress(ctx, "simulate", 4 + len(sp.pictures)) as advance:
        started = []

        def step(message):
            ctx.info(message)
            advance(1 if started else 0, description=f"simulate: {message}")
            started.append(message)

        result = simulate(sp, outdir, overwrite=overwrite, progress=step, max_memory=limit)
        advance(1, description="simulate: done")
    table = truth_table(result.truth)
    table.command = f"simulate {spec} {outdir}"
    table.meta["outdir"] = str(outdir)
    table.meta["files"] = len(result.files)
    emit_table(table, as_json=as_json, output=output)


def _parse_size(text: str) -> int:
    """Bytes of ``8G``, ``500M``, ``2GiB``, ``1e9`` (K, M, G, T are powers of 1024)."""
    import re

    number = r"([0-9]*\.?[0-9]+(?:[eE][+-]?[0-9]+)?)"
    m = re.fullmatch(rf"\s*{number}\s*([KMGT]?)(?:i?B)?\s*", str(text), re.IGNORECASE)
    if not m:
        raise SpcUsageError(f"--max-memory: expected a size such as 8G or 500M, got {text!r}")
    value = float(m.group(1)) * 1024 ** "KMGT".find(m.group(2).upper()) * (1024 if m.group(2) else 1)
    if not 0 < value < 2**63:
        raise SpcUsageError(f"--max-memory: expected a positive size, got {text!r}")
    return int(value)


def truth_table(truth: dict):
    """Landmark table of a TRUTH.json document: one row per landmark and picture."""
    from spctool.formats.table import LandmarkTable

    rows = []
    for lm in truth["landmarks"]:
        for pic, px in lm["pixels"].items():
            status = (
                "outside"
                if not px["in_image"]
                else "occluded"
                if not px["visible"]
                else "shadowed"
                if px["shadowed"]
                else "ok"
            )
            rows.append(
                {
                    "name": lm["name"],
                    "picture": pic,
                    "true_sample": px["sample"],
                    "true_line": px["line"],
                    "emission": px["emission_deg"],
                    "incidence": px["incidence_deg"],
                    "phase": px["phase_deg"],
                    "status": status,
                }
            )
    return LandmarkTable.from_rows(rows)


def example_spec() -> str:
    """A SPEC.toml with every key at its default (comments carry the help text)."""
    import json

    from spctool.sim.spec_keys import DEFAULT_PICTURES, PICTURE_KEYS, SPEC_KEYS

    def val(v):
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, str):
            return json.dumps(v)
        return json.dumps(v)

    lines = ["# spctool simulate SPEC (every key optional; these are the defaults)"]
    current = None
    for section, key, default, _kind, text in SPEC_KEYS:
        if section != current:
            current = section
            if section:
                lines += ["", f"[{section}]"]
        lines.append(f"{key} = {val(default)}  # {text}")
    keys = [k for k, *_ in PICTURE_KEYS]
    for p in DEFAULT_PICTURES:
        lines += ["", "[[pictures]]"]
        for k in keys:
            if k in p:
                lines.append(f"{k} = {val(p[k])}")
    lines.append("")
    lines.append("# [[pictures]] keys: " + ", ".join(keys))
    return "\n".join(lines) + "\n"


# ------------------------------------------------------------------------------------------------
# make-maplets
# ------------------------------------------------------------------------------------------------


@click.command("make-maplets")
@click.argument("landmarks", nargs=-1, shell_complete=options.complete_landmark)
@click.option(
    "--at",
    "at",
    multiple=True,
    nargs=4,
    type=(str, float, float, float),
    metavar="NAME X Y Z",
    help="A new landmark NAME at body-fixed VLM (X, Y, Z) km (repeatable).",
)
@click.option(
    "--tile",
    "tile",
    type=options.FINITE_FLOAT,
    default=None,
    metavar="SPACING_KM",
    help="Tile the whole body with new landmarks about SPACING_KM apart.",
)
@click.option("--prefix", default="TL", show_default=True, help="Name prefix of tiled landmarks.")
@click.option(
    "--scale",
    type=options.FINITE_FLOAT,
    default=None,
    metavar="KM",
    help="Maplet SCALE (km per cell). Default: each LMK's own (required for --at/--tile).",
)
@click.option(
    "--qsz", type=int, default=None, help="Maplet QSZ. Default: each LMK's own (required for --at/--tile)."
)
@options.shape_option()
@click.option(
    "--keep-frame",
    is_flag=True,
    help="Existing landmarks keep their VLM and UX/UY/UZ (only the heights are projected).",
)
@click.option("--no-lmrklist", is_flag=True, help="Do not add new landmarks to LMRKLIST.TXT.")
@click.option(
    "--overwrite", is_flag=True, help="Replace existing MAP files (and LMK files of new landmarks)."
)
@options.json_option
@options.output_option
@pass_context
def make_maplets_cmd(
    ctx: Context,
    landmarks,
    at,
    tile,
    prefix,
    scale,
    qsz,
    shape_path,
    keep_frame,
    no_lmrklist,
    overwrite,
    as_json,
    output,
):
    """Maplets from the working directory's shape, as SPC's GET_HEIGHTS projects it.

    Every node's vertical line (along -UZ) is intersected with the shape and the highest surface
    point is kept; the albedo is the ICQ 4th column (or 1). New landmarks
    (--at, --tile) get SPC's ORIENT frame at the shape's fitted normal (UY East, UX South) and V on
    the surface; LANDMARKS named on the command line (LMKFILES/NAME.LMK) are re-framed the same way
    unless --keep-frame. Writes MAPFILES/NAME.MAP and LMKFILES/NAME.LMK, and adds new names to
    LMRKLIST.TXT.

    Columns (one row per maplet): name, latitude and longitude (degrees, of V), radius_km (|V|),
    scale_km (cell size), qsz (half-size, cells), valid_fraction (nodes that met the shape), hmin
    and hmax (lowest and highest height, cells), status.

    The examples run on copies of the demo: they add or replace maplets (made from the shape, so
    coarser than the demo's own), which changes every later registration in that directory.

    Examples:

    \b
      spctool demo --copy-to tiles && spctool -C tiles make-maplets --tile 0.1 --scale 0.0005 --qsz 24
      spctool demo --copy-to at && spctool -C at make-maplets --at AA0001 0.21 0.05 0.1 --scale 0.001 --qsz 49
      spctool demo --copy-to framed && spctool -C framed make-maplets B01980 B02176 --keep-frame --overwrite
    """
    from spctool.formats.landmark import read_lmk, write_lmk
    from spctool.formats.lists import LandmarkList, read_lmrklist, write_lmrklist
    from spctool.formats.maplet import write_map
    from spctool.geometry.surfaces import ShapeSurface
    from spctool.sim.maplets import landmark_names, make_maplets, surface_points, tile_count, tile_directions

    wd = ctx.wd
    model = wd.read_shape(shape_path)
    if model is None:
        raise SpcUsageError(f"no shape model: give --shape or put one in {wd.shape_path}")
    surf = ShapeSurface.from_model(model)
    jobs = []  # (name, centre, scale, qsz, frames or None, existing Landmark or None)
    for name in landmarks:
        lmk = read_lmk(wd.lmk_path(name)) if not Path(name).is_file() else read_lmk(name)
        s = scale if scale is not None else lmk.scale
        q = qsz if qsz is not None else lmk.qsz
        frames = (lmk.ux, lmk.uy, lmk.uz) if keep_frame else None
        jobs.append((lmk.name, lmk.vlm, s, q, frames, lmk))
    new_names = []
    if at or tile is not None:
        if scale is None or qsz is None:
            raise SpcUsageError("--at and --tile need --scale and --qsz")
    for name, x, y, z in at:
        jobs.append((name, np.array([x, y, z]), scale, qsz, None, None))
        new_names.append(name)
    if tile is not None:
        n = tile_count(surf, tile)
        pts = surface_points(surf, tile_directions(n))
        pts = pts[np.all(np.isfinite(pts), axis=1)]
        for name, p in zip(landmark_names(prefix, pts.shape[0]), pts):
            jobs.append((name, p, scale, qsz, None, None))
            new_names.append(name)
    if not jobs:
        raise SpcUsageError("nothing to do: name landmarks, or use --at or --tile")
    names = [j[0] for j in jobs]
    if len(set(names)) != len(names):
        raise SpcUsageError("a landmark name is given twice")
    if not overwrite:
        exist = [n for n in names if wd.map_path(n).exists()] + [
            n for n in new_names if wd.lmk_path(n).exists()
        ]
        if exist:
            raise SpcUsageError(f"{len(exist)} MAP/LMK files exist (e.g. {exist[0]}); use --overwrite")
    # group by (scale, qsz, keep-frame) so each group is one batched projection
    groups: dict = {}
    for j in jobs:
        groups.setdefault((j[2], j[3], j[4] is not None), []).append(j)
    results = {}
    with progress(ctx, "make-maplets", len(jobs)) as advance:
        for (s, q, keep), group in groups.items():
            for c0 in range(0, len(group), 64):  # each maplet is independent: chunks for the progress bar
                chunk = group[c0 : c0 + 64]
                frames = None
                if keep:
                    frames = tuple(np.array([g[4][a] for g in chunk]) for a in range(3))
                centres = np.array([g[1] for g in chunk])
                made = make_maplets(surf, [g[0] for g in chunk], centres, s, q, frames=frames)
                for g, (m, lm) in zip(chunk, made):
                    results[g[0]] = (m, lm, g[5])
                advance(len(chunk))
    (wd.root / "MAPFILES").mkdir(parents=True, exist_ok=True)
    (wd.root / "LMKFILES").mkdir(parents=True, exist_ok=True)
    rows = []
    for name in names:
        m, lm, old = results[name]
        write_map(wd.map_path(name), m, backup=True)  # a replaced file is kept as .bak
        if old is not None:
            old.vlm, old.ux, old.uy, old.uz = lm.vlm, lm.ux, lm.uy, lm.uz
            old.scale, old.qsz = lm.scale, lm.qsz
            lm = old
        write_lmk(wd.lmk_path(name), lm, backup=True)
        v = np.asarray(lm.vlm)
        r = float(np.linalg.norm(v))
        hv = m.heights[m.valid]
        rows.append(
            {
                "name": name,
                "latitude": math.degrees(math.asin(v[2] / r)),
                "longitude": math.degrees(math.atan2(v[1], v[0])) % 360.0,
                "radius_km": r,
                "scale_km": m.scale,
                "qsz": m.qsz,
                "valid_fraction": float(m.valid.mean()),
                "hmin": float(hv.min()) if hv.size else float("nan"),
                "hmax": float(hv.max()) if hv.size else float("nan"),
                "status": "ok",
            }
        )
    if new_names and not no_lmrklist:
        path = wd.lmrklist_path
        llist = read_lmrklist(path) if path.exists() else LandmarkList([])
        have = set(llist.names)
        llist.names.extend(n for n in new_names if n not in have)
        write_lmrklist(path, llist)
    from spctool.formats.table import LandmarkTable

    table = LandmarkTable.from_rows(rows, command="make-maplets")
    emit_table(table, as_json=as_json, output=output)


# ------------------------------------------------------------------------------------------------
# render
# ------------------------------------------------------------------------------------------------


@click.command("render")
@click.argument("picture", shell_complete=options.complete_picture)
@click.argument("landmarks", nargs=-1, shell_complete=options.complete_landmark)
@click.option(
    "-o",
    "--output",
    "out",
    required=True,
    type=click.Path(dir_okay=False),
    help="Photo file to write (.DAT, .FITS, .PGM or .PNG; see --format).",
)
@click.option(
    "--format",
    "fmt",
    type=click.Choice(["dat", "fits", "pgm", "png"]),
    default=None,
    help="Photo format. Default: from the extension of --output.",
)
@options.shape_option()
@click.option("--no-shape", is_flag=True, help="Render the maplets alone.")
@click.option("--no-maplets", is_flag=True, help="Render the shape alone.")
@options.photometry_option
@click.option(
    "--supersample", type=click.IntRange(1, 16), default=2, show_default=True, help="n x n rays per pixel."
)
@click.option("--no-shadows", is_flag=True, help="Do not trace cast shadows.")
@click.option("--bits", type=click.Choice(["8", "16"]), default="16", show_default=True, help="DN bits.")
@click.option("--float", "as_float", is_flag=True, help="Write the radiance itself as float32 (FITS only).")
@click.option(
    "--exposure",
    default="auto",
    show_default=True,
    help="DN of radiance 1, or 'auto' (99.5th percentile at 80 % of full scale).",
)
@click.option("--noise", is_flag=True, help="Add shot and read noise (40000 e- full well, 20 e- read noise).")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the noise.")
@click.option(
    "--window",
    nargs=4,
    type=int,
    default=None,
    metavar="S0 S1 L0 L1",
    help="Render only samples S0..S1 and lines L0..L1 (1-based, inclusive); the rest is 0.",
)
@pass_context
def render_cmd(
    ctx: Context,
    picture,
    landmarks,
    out,
    fmt,
    shape_path,
    no_shape,
    no_maplets,
    photometry,
    supersample,
    no_shadows,
    bits,
    as_float,
    exposure,
    noise,
    seed,
    window,
):
    """A synthetic photo of the working directory's shape and maplets at PICTURE's SUM pose.

    Ray-traces the shape (SHAPEFILES/SHAPE.TXT, its albedo column) and the maplets (LANDMARKS, or
    every landmark of LMRKLIST.TXT with a MAP file) through the picture's camera (SUM pose,
    K-matrix, INIT_LITHOS DISTORT= model), with cast shadows and the chosen illumination function;
    inside a maplet's footprint the maplet replaces the shape. The Sun is the SUM's SZ. DN 0 is
    sky (no data); the body is >= 1.

    Example:

    \b
      spctool -C demo render P000000001A1 -o render.fits
      spctool -C demo render P000000001A1 B01980 --no-shape --float -o b01980.fits
    """
    from spctool.formats.photo import Photo, write_photo
    from spctool.geometry.surfaces import HeightPatch
    from spctool.sim.simulate import Detector, expose
    from spctool.stages.render import RenderOptions, cull_patches, render

    wd = ctx.wd
    _, pic, _, camera = load_picture(ctx, picture)
    model = None
    if not no_shape:
        model = wd.read_shape(shape_path)
        if model is None:
            ctx.note_once("no shape model: rendering the maplets alone")
    patches = []
    if not no_maplets:
        names = list(landmarks) if landmarks else [n for n in wd.landmark_names() if wd.map_path(n).exists()]
        maps = [wd.read_maplet(n) for n in names]
        patches = cull_patches(
            camera, [HeightPatch.from_maplet(m, name=n) for m, n in zip(maps, names)], window
        )
        ctx.info(f"{len(patches)} of {len(names)} maplets in view")
    if model is None and not patches:
        raise SpcUsageError("nothing to render: no shape and no maplet in view")
    render_options = RenderOptions(photometry=photometry, supersample=supersample, shadows=not no_shadows)
    lines = camera.nln if window is None else max(0, int(window[3]) - int(window[2]) + 1)
    with progress(ctx, f"render {pic.name}", lines) as advance:
        r = render(camera, pic.sz, model, patches, render_options, window=window, progress=advance)
    if fmt is None:
        ext = Path(out).suffix.lower().lstrip(".")
        fmt = {"fit": "fits", "fts": "fits"}.get(ext, ext)
        if fmt not in ("dat", "fits", "pgm", "png"):
            raise SpcUsageError(f"{out}: cannot tell the photo format from the extension (use --format)")
    full = np.zeros((camera.nln, camera.npx))
    cov = np.zeros((camera.nln, camera.npx))
    s0, s1, l0, l1 = r.window
    full[l0 - 1 : l1, s0 - 1 : s1] = r.radiance
    cov[l0 - 1 : l1, s0 - 1 : s1] = r.coverage
    if as_float:
        if fmt != "fits":
            raise SpcUsageError("--float needs a FITS output")
        data = full.astype(np.float32)
    else:
        expo = exposure if exposure == "auto" else float(exposure)
        det = Detector(bits=int(bits), exposure=expo)
        rng = np.random.default_rng(seed) if noise else None
        data, _ = expose(full, cov, det, rng)
    header = {"PICTURE": (pic.name, "SPC picture name"), "ORIGIN": ("spctool render", "synthetic")}
    write_photo(
        out, Photo(data, name=pic.name), fmt=fmt, header=header if fmt == "fits" else None, backup=True
    )
    ctx.info(f"wrote {out}")


# ------------------------------------------------------------------------------------------------
# demo


@click.command("demo")
@click.option(
    "--copy-to",
    "copy_to",
    metavar="DIR",
    type=click.Path(file_okay=False),
    help="Copy the demo working directory to DIR (to play with) and stop.",
)
@click.option(
    "--force",
    is_flag=True,
    help="With --copy-to: copy into a DIR that is not empty; each demo file already there that differs "
    "is kept as FILE.bak, other files are left alone.",
)
@click.option(
    "--workdir",
    "workdir",
    metavar="DIR",
    type=click.Path(file_okay=False, exists=True),
    help="Run on this simulated working directory (with TRUTH.json) instead of the shipped demo.",
)
@options.space_option
@options.pipeline_schedule_option
@options.sigma_px_option(
    0.2, help="1-sigma landmark pixel error given to the pose solve (see the description)."
)
@click.option(
    "--keep",
    "keep",
    metavar="DIR",
    type=click.Path(file_okay=False),
    help="Also write the updated SUM files and stage tables under DIR (batch layout).",
)
@options.json_option
@options.output_option
@pass_context
def demo_cmd(ctx: Context, copy_to, force, workdir, space, schedule, sigma_px, keep, as_json, output):
    """Run lithos-select -> register -> solve-pose on the shipped demo and print errors against truth.

    The demo is a small simulated SPC working directory installed with spctool (twelve maplets,
    four photos with a-priori poses a few pixels off, OWEN distortion, TRUTH.json). Exit code 1
    when a pose component of some picture lies outside 3 sigma.

    Columns (one row per picture): picture; selected (maplets lithos-select chose); found
    (landmarks registered); status (ok, no-pose, failed: ..., outside-3sigma); pixel_rms and
    pixel_max (registered minus true landmark pixel, px); position_error_m (solved minus true
    spacecraft position, m) beside position_3sigma_m (3 x the reported 1-sigma, m) and
    apriori_position_error_m (the SUM's a-priori error, m); attitude_error_urad and
    attitude_3sigma_urad (the same for the camera attitude, microradians); max_normalised_error
    (largest |error| / 1-sigma over the six pose components); nees (normalised estimation error
    squared: e' C^-1 e of the 6-component pose error e with the reported covariance C; about 6
    on average when C is honest, much larger when it is overconfident); within_3sigma (every
    component within 3 sigma).  --json writes {"pictures": [{"picture": ..., ...}]} like batch.

    The pose solve weighs each landmark pixel with --sigma-px (default 0.2 px): registration against
    maplets that are smoothed, coarser versions of the truth errs by about 0.1 px per axis with biases
    that do not average out (Shoemaker et al. 2016, Table 3: biases up to 0.2 px, 1-sigma up to 0.11
    px), so the solver's 0.1 px default would understate the pose covariance here.

    Example:

    \b
      spctool demo
      spctool demo --space image --json
      spctool demo --copy-to mydemo && spctool -C mydemo lithos-select P000000001A1
      spctool demo --copy-to mydemo --force  # a fresh demo over an old copy (replaced files: .bak)
    """
    import tempfile

    from spctool.batch import BatchOptions, navigate_picture, write_outcome
    from spctool.formats.table import LandmarkTable
    from spctool.sim.demo import copy_demo, demo_path, picture_errors, read_truth
    from spctool.stages.register import RegisterOptions

    if copy_to:
        dest = Path(copy_to)
        if dest.is_dir() and any(dest.iterdir()) and not force:
            raise SpcUsageError(
                f"--copy-to {copy_to}: directory is not empty (--force copies the demo into it, keeping "
                "each file it replaces as FILE.bak; or name a new directory)"
            )
        copy_demo(dest, overwrite=force)
        click.echo(f"demo working directory copied to {dest}")
        return
    if force:
        raise SpcUsageError("--force goes with --copy-to DIR")
    root = Path(workdir) if workdir else demo_path()
    truth = read_truth(root)
    from spctool.stages.pose import PoseOptions

    pose_options = PoseOptions(sigma_px=sigma_px)
    reg = RegisterOptions(schedule=options.register_schedule(schedule), space=space, pose=pose_options)
    batch_options = BatchOptions(register=reg, pose=pose_options, two_pass=None)  # its --schedule
    pictures = [p["name"] for p in truth["pictures"]]
    rows = []
    with tempfile.TemporaryDirectory(prefix="spctool-demo-") as tmp:
        src = root
        if not workdir:  # never run in the installed package folder
            src = copy_demo(Path(tmp) / "demo")
        with progress(ctx, "demo", len(pictures)) as advance:
            for name in pictures:
                outcome = navigate_picture(src, name, batch_options)
                advance()
                summary = outcome.summary
                row = {
                    "picture": name,
                    "selected": summary.selected,
                    "found": summary.found,
                    "status": summary.status,
                }
                if outcome.pose is not None and outcome.register is not None:
                    reg_res = outcome.register
                    measured = {
                        n: tuple(m) for n, m, ok in zip(reg_res.names, reg_res.measured, reg_res.ok) if ok
                    }
                    e = picture_errors(
                        truth,
                        name,
                        outcome.pose.position,
                        outcome.pose.rotation,
                        outcome.pose.covariance,
                        measured,
                    )
                    row.update(
                        pixel_rms=e["pixel_rms"],
                        pixel_max=e["pixel_max"],
                        position_error_m=1e3 * float(np.linalg.norm(e["position_error_km"])),
                        position_3sigma_m=3e3 * float(np.linalg.norm(e["sigma_position_km"])),
                        apriori_position_error_m=1e3 * float(np.linalg.norm(e["apriori_position_error_km"])),
                        attitude_error_urad=1e6 * float(np.linalg.norm(e["attitude_error_rad"])),
                        attitude_3sigma_urad=3e6 * float(np.linalg.norm(e["sigma_attitude_rad"])),
                        max_normalised_error=float(np.max(np.abs(e["normalised_error"]))),
                        nees=e["nees"],
                        within_3sigma=e["within_3sigma"],
                    )
                    if not e["within_3sigma"]:
                        row["status"] = "outside-3sigma"
                if keep:
                    write_outcome(keep, outcome, batch_options.fingerprint())
                rows.append(row)
    table = LandmarkTable.from_rows(rows, command="demo", meta={"space": space, "schedule": schedule})
    if as_json:  # one object per picture under "pictures", as batch writes them
        import json

        doc = table.to_json_dict()
        del doc["picture"]
        doc["pictures"] = doc.pop("landmarks")
        emit(json.dumps(doc, indent=2, allow_nan=False) + "\n", output)
    else:
        emit_table(table, as_json=False, output=output)
    if any(r.get("within_3sigma") is not True for r in rows):
        raise click.exceptions.Exit(1)


def register(cli):
    cli.add_command(simulate_cmd)
    cli.add_command(make_maplets_cmd)
    cli.add_command(render_cmd)
    cli.add_command(demo_cmd)
