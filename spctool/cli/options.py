"""Command-line options that several commands share, declared once (cli-contract.md "Options").

Each option that means the same thing in two commands is declared here, with one name, one help
text and one default; option *groups* (several options that always travel together, e.g. the
Stage B prediction options) are decorators made with :func:`option_group`.  Next to a group stands
the builder that turns its parsed values into the stage's options dataclass, so the mapping from
command-line names to stage fields is written once too:

* picture inputs: ``PICTURE``, ``[LANDMARK]...``, ``--sum``, ``--photo``, ``--flip-rows``,
  ``--landmarks TABLE``, ``--shape``;
* output: ``--json``, ``-o/--output``, ``--out-dir``/``--image-format`` (stage images), ``--overlay``,
  ``--require``;
* Stage B (predict, spc-algorithms.md 3) and Stages C-E (extract, spc-algorithms.md 4-6):
  :data:`predict_options`, :data:`extract_options`, :func:`predict_extract_options`, ``--thresholds``
  with :func:`picture_thresholds`;
* registration: ``--space``, ``--corr-min``, the pipeline ``--schedule`` and :func:`register_schedule`;
* Stage I (pose solve, spc-algorithms.md 10): ``--sigma-px``, ``--no-prior``, ``--min-landmarks`` and
  :func:`pose_options`.

Parameter names (the Python names click passes) are part of each option's definition: a command
using an option here receives it under the same name everywhere (``sum_path``, ``photo_path``,
``shape_path``, ``landmarks_table``, ``as_json``, ``output`` ...).
"""

from __future__ import annotations

import math

import click

from spctool.errors import SpcUsageError

IMAGE_FORMATS = ("pgm", "png", "fits")


class _Finite:
    """Refuses NaN and ±inf after the float type it is mixed into has converted the value (exit 2,
    naming the option): a NaN passes every comparison of a range check and ended a solve in an
    internal error, or in a silent wrong answer."""

    def convert(self, value, param, ctx):
        v = super().convert(value, param, ctx)
        if not math.isfinite(v):
            self.fail(f"{value!r} is not a finite number", param, ctx)
        return v


class FiniteFloatRange(_Finite, click.FloatRange):
    """click's FloatRange, finite."""


class FiniteFloat(_Finite, click.types.FloatParamType):
    """click's float, finite."""


#: a float option that must be finite (``type=FINITE_FLOAT`` where ``type=float`` would take NaN)
FINITE_FLOAT = FiniteFloat()
PHOTOMETRY_LAWS = ("spc", "mcewen", "fixed", "lambert")


def option_group(*decorators):
    """One decorator applying ``decorators`` as if stacked in this order above a function."""

    def apply(f):
        for d in reversed(decorators):
            f = d(f)
        return f

    return apply


# ------------------------------------------------------------------------------------------------
# output


json_option = click.option("--json", "as_json", is_flag=True, help="Write one JSON document instead of text.")

output_option = click.option(
    "-o",
    "--output",
    "output",
    metavar="FILE",
    default=None,
    help="Write the table to FILE instead of stdout ('-' = stdout).",
)


def out_dir_option(help: str):
    """``--out-dir DIR``: where a stage writes one image per landmark."""
    return click.option("--out-dir", type=click.Path(file_okay=False), default=None, metavar="DIR", help=help)


image_format_option = click.option(
    "--image-format",
    type=click.Choice(IMAGE_FORMATS),
    default="pgm",
    show_default=True,
    help="Format of the --out-dir images (FITS keeps the float values and a header).",
)

image_zoom_option = click.option(
    "--zoom",
    "zoom",
    type=click.IntRange(1, 64),
    default=1,
    show_default=True,
    metavar="N",
    help="Enlarge the PGM/PNG --out-dir images N times, each cell an NxN block (FITS keeps the data).",
)


def overlay_option(help: str):
    """``--overlay FILE.png``: the photo with the command's results drawn on it."""
    return click.option(
        "--overlay", "overlay", metavar="FILE.png", type=click.Path(dir_okay=False), help=help
    )


def acquire_reach_option(help: str, default: int | None):
    """``--acquire-reach CELLS`` (RegisterOptions.acquire_reach): the first step's search on the photo
    resampled beyond the maplet's edge."""
    return click.option(
        "--acquire-reach", "acquire_reach", type=click.IntRange(min=0), default=default,
        show_default=default is not None, metavar="CELLS", help=help,
    )  # fmt: skip


def first_phases_option(help: str, default: int | None):
    """``--first-phases P`` (RegisterOptions.first_phases): the first step at P × P phases."""
    return click.option(
        "--first-phases", "first_phases", type=click.IntRange(1, 4), default=default,
        show_default=default is not None, metavar="P", help=help,
    )  # fmt: skip


def reach_option(help: str, default: float | None):
    """``--reach PX`` (NavigateOptions.reach_px): how far two-pass navigation's acquisition reaches."""
    return click.option(
        "--reach", "reach_px", type=FiniteFloatRange(min=1.0), default=default,
        show_default=default is not None, metavar="PX", help=help,
    )  # fmt: skip


def require_option(help: str):
    """``--require N``: exit 1 (SpcResultError) when the command found fewer than N."""
    return click.option(
        "--require", "require", type=click.IntRange(min=0), default=None, metavar="N", help=help
    )


def check_require(picture: str, found: int, require, what: str) -> None:
    """The ``--require N`` check: SpcResultError (exit 1) naming ``found`` ``what`` when below N."""
    if require is not None and found < require:
        from spctool.errors import SpcResultError

        raise SpcResultError(f"{picture}: {found} {what}, fewer than --require {require}")


# ------------------------------------------------------------------------------------------------
# inputs: picture, photo, landmarks, shape


def complete_picture(ctx, param, incomplete):
    """Shell completion: the working directory's picture names (:mod:`spctool.cli.completion`)."""
    from spctool.cli import completion

    return completion.complete_picture(ctx, param, incomplete)


def complete_landmark(ctx, param, incomplete):
    """Shell completion: the working directory's landmark names (:mod:`spctool.cli.completion`)."""
    from spctool.cli import completion

    return completion.complete_landmark(ctx, param, incomplete)


picture_argument = click.argument("picture", shell_complete=complete_picture)

landmark_names_argument = click.argument(
    "names", nargs=-1, metavar="[LANDMARK]...", shell_complete=complete_landmark
)

sum_option = click.option(
    "--sum",
    "sum_path",
    metavar="FILE",
    type=click.Path(dir_okay=False),
    help="The picture's SUM file (default: PIC itself if it is a .SUM path, else DIR/SUMFILES/PIC.SUM).",
)


any_picture_option = click.option(
    "--any-picture",
    "any_picture",
    is_flag=True,
    help="Use a landmark table whose '# picture:' header, or a --sum file whose picture name, is "
    "another picture's (default: refused, exit 2).",
)


def photo_option(purpose: str = ""):
    """``--photo FILE``; ``purpose`` (e.g. ``" for --overlay"``) follows 'The photo' in the help."""
    return click.option(
        "--photo",
        "photo_path",
        metavar="FILE",
        type=click.Path(dir_okay=False, exists=True),
        help=f"The photo{purpose} (FITS, PGM, PNG or .DAT). Default: the picture's IMAGEFILES/ photo.",
    )


flip_rows_option = click.option(
    "--flip-rows",
    is_flag=True,
    help="The photo's rows are stored bottom-up: read line 1 from the last stored row.",
)


def landmarks_table_option(help: str):
    """``--landmarks TABLE``: landmarks from a landmark table ('-' = stdin)."""
    return click.option(
        "--landmarks",
        "landmarks_table",
        metavar="TABLE",
        type=click.Path(dir_okay=False, allow_dash=True),
        help=help,
    )


def shape_option(purpose: str = "", *, exists: bool = False):
    """``--shape FILE``; ``purpose`` (e.g. ``" for the occlusion test"``) follows 'Shape model'."""
    return click.option(
        "--shape",
        "shape_path",
        metavar="FILE",
        type=click.Path(dir_okay=False, exists=exists),
        help=f"Shape model{purpose} (ICQ, OBJ or VTK). Default: DIR/SHAPEFILES/SHAPE.TXT when present.",
    )


# ------------------------------------------------------------------------------------------------
# Stage B (predict) and Stages C-E (extract)


photometry_option = click.option(
    "--photometry",
    type=click.Choice(PHOTOMETRY_LAWS),
    default="spc",
    show_default=True,
    help="Illumination law: SPC lunar-Lambert (no factor 2), McEwen, SPC form with fixed beta, Lambert.",
)

shadows_option = click.option(
    "--shadows",
    type=click.Choice(["auto", "spc", "cast"]),
    default="auto",
    show_default=True,
    help="spc: dark only where the incidence exceeds 90 deg; cast: also ray-marched cast shadows over "
    "the maplet; auto: cast where the photo shows a maplet's cast shadows above THRSH T1 (which SPC's "
    "rule would call lit), else spc.",
)

linearized_option = click.option(
    "--linearized",
    is_flag=True,
    help="Project nodes with the linearisation about the landmark of Shoemaker et al. 2016 (default: the "
    "full camera model).",
)

no_filter_option = click.option(
    "--no-filter",
    "no_filter",
    is_flag=True,
    help="Skip the extract filter (shadow enhancement, emission cut, visibility march).",
)

thresholds_option = click.option(
    "--thresholds",
    default=None,
    metavar="T1,T2",
    help="DN range used from the photo (default: the SUM THRSH).",
)


def criteria_option(help: str, default: str | None = None):
    """``--criteria SPEC``: the extract removal criteria (a name or 'INVLIM,SLIM,CLIM,[ILIM,]RSMN,RSMX')."""
    shown = {"show_default": True} if default is not None else {}
    return click.option("--criteria", default=default, metavar="SPEC", help=help, **shown)


#: Stage B options (all of PredictOptions)
predict_options = option_group(
    photometry_option,
    click.option(
        "--beta",
        type=FINITE_FLOAT,
        default=0.65,
        show_default=True,
        metavar="B",
        help="Constant beta of --photometry fixed.",
    ),
    click.option(
        "--alpha0",
        type=FINITE_FLOAT,
        default=60.0,
        show_default=True,
        metavar="DEG",
        help="beta = exp(-phase/alpha0).",
    ),
    shadows_option,
    click.option(
        "--bg-corr-min",
        type=FINITE_FLOAT,
        default=1.0,
        show_default=True,
        metavar="RHO",
        help="Fit the background phi when the zero-offset correlation exceeds RHO (>= 1: never).",
    ),
)

#: Stages C-E options (all of ExtractOptions)
extract_options = option_group(
    linearized_option,
    click.option(
        "--subsample",
        default="auto",
        show_default=True,
        metavar="auto|M",
        help="Average MxM samples per cell (auto: ceil(sqrt|det J|) when cells exceed pixels).",
    ),
    no_filter_option,
    click.option(
        "--ds-mode",
        type=click.Choice(["seed", "sqrt"]),
        default="seed",
        show_default=True,
        help="Shadow extension ds = base + floor(1/|det J|) (seed) or floor(1/sqrt|det J|).",
    ),
    click.option(
        "--ds-base",
        type=click.IntRange(min=0),
        default=3,
        show_default=True,
        metavar="N",
        help="Base shadow extension in cells.",
    ),
    click.option(
        "--lateral",
        type=click.IntRange(min=0),
        default=2,
        show_default=True,
        metavar="N",
        help="Lateral widening of the shadow extension in cells.",
    ),
    click.option(
        "--cos-e-min",
        type=FINITE_FLOAT,
        default=0.05,
        show_default=True,
        metavar="C",
        help="Zero cells whose normal makes cos(emission) < C.",
    ),
    click.option(
        "--vis-tol",
        type=FINITE_FLOAT,
        default=0.05,
        show_default=True,
        metavar="CELLS",
        help="Lowering of the visibility ray march.",
    ),
    click.option(
        "--cast-shadow-trace",
        is_flag=True,
        help="Also zero cells in cast shadow by a march toward the Sun (SPC skips it).",
    ),
    criteria_option(
        "Removal criteria: lithos_standard, autoregister, or 'INVLIM,SLIM,CLIM,ILIM,RSMN,RSMX' "
        "(5 values: AUTOREGISTER's form without ILIM).",
        default="lithos_standard",
    ),
    click.option("--no-removal", is_flag=True, help="Report the statistics but never a removed-* status."),
    click.option(
        "--ill-source",
        type=click.Choice(["extracted", "predicted"]),
        default="extracted",
        show_default=True,
        help="ILL counts non-zero cells of the extracted or predicted image.",
    ),
    thresholds_option,
)

# command-line parameter -> PredictOptions / ExtractOptions field (same value)
_PREDICT_FIELDS = {
    "photometry": "photometry",
    "beta": "beta",
    "alpha0": "alpha0_deg",
    "shadows": "shadows",
    "bg_corr_min": "bg_corr_min",
}
_EXTRACT_FIELDS = {
    "linearized": "linearized",
    "subsample": "subsample",
    "ds_mode": "ds_mode",
    "ds_base": "ds_base",
    "lateral": "lateral",
    "cos_e_min": "cos_e_min",
    "vis_tol": "vis_tol",
    "cast_shadow_trace": "cast_shadow_trace",
    "ill_source": "ill_source",
}


def predict_extract_options(kw: dict, criteria):
    """(PredictOptions, ExtractOptions) from a command's parsed options.

    Every Stage B / C-E option the command declares (any subset of :data:`predict_options` and
    :data:`extract_options`) is taken from ``kw``; the others keep the stage defaults.  ``criteria``
    (a spec text or ``None`` = no removal) is the command's reading of its ``--criteria``.
    """
    from spctool.stages.extract import ExtractOptions
    from spctool.stages.predict import PredictOptions

    predict = PredictOptions(**{field: kw[name] for name, field in _PREDICT_FIELDS.items() if name in kw})
    extract = {field: kw[name] for name, field in _EXTRACT_FIELDS.items() if name in kw}
    if "no_filter" in kw:
        extract["apply_filter"] = not kw["no_filter"]
    return predict, ExtractOptions(**extract, criteria=criteria)


def picture_thresholds(text: str | None, pic) -> tuple[float, float]:
    """The DN range of ``--thresholds T1,T2``, else the picture's SUM THRSH."""
    if text is None:
        return tuple(float(x) for x in pic.thrsh)
    parts = [p for p in text.replace(",", " ").split() if p]
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        values = ()
    if len(values) != 2 or not all(math.isfinite(v) for v in values) or not values[0] < values[1]:
        raise SpcUsageError(f"--thresholds expects two finite numbers T1,T2 with T1 < T2, got {text!r}")
    return values


# ------------------------------------------------------------------------------------------------
# registration (Stages F-H)


space_option = click.option(
    "--space",
    type=click.Choice(["maplet", "image"]),
    default="maplet",
    show_default=True,
    help="maplet: the photo resampled onto the maplet (SPC); image: the maplet rendered into the photo "
    "with cast shadows and correlated over the photo (as the Retina system does, Wright et al. 2016).",
)

corr_min_option = click.option(
    "--corr-min",
    type=FINITE_FLOAT,
    default=0.3,
    show_default=True,
    metavar="RHO",
    help="Correlation peaks below RHO are low-correlation (0.3 as in Shoemaker et al. 2016 and NASA GIANT).",
)

#: --schedule of the whole-pipeline commands (batch, demo); 'register' offers retina_s16 too
pipeline_schedule_option = click.option(
    "--schedule",
    type=click.Choice(["autoregister", "s16"]),
    default="autoregister",
    show_default=True,
    help="Registration schedule: SPC's AUTOREGISTER (pose solve after each pass) or the "
    "per-landmark spacings 10..1 of Shoemaker et al. 2016 (see 'spctool register --help').",
)


def register_schedule(name: str) -> str:
    """The RegisterOptions schedule of a --schedule choice (s16 is the stage's retina_s16)."""
    return "retina_s16" if name in ("s16", "retina_s16") else "autoregister"


# ------------------------------------------------------------------------------------------------
# Stage I (pose solve)


def sigma_px_option(default: float = 0.1, help: str | None = None):
    """``--sigma-px PX``: the pose solve's 1-sigma pixel noise."""
    return click.option(
        "--sigma-px",
        type=FINITE_FLOAT,
        default=default,
        show_default=True,
        metavar="PX",
        help=help
        or "1-sigma measurement noise per pixel component of the pose solve (Shoemaker et al. 2016: "
        "0.1 px; 1 px is conservative).",
    )


no_prior_option = click.option(
    "--no-prior",
    is_flag=True,
    help="Ignore the SUM's SIGMA_VSO / SIGMA_PTG a-priori constraint in the pose solve (needs >= 3 "
    "landmarks).",
)

min_landmarks_option = click.option(
    "--min-landmarks",
    type=click.IntRange(min=0),
    default=3,
    show_default=True,
    metavar="N",
    help="Fewer usable landmarks leave the pose unsolved.",
)


def _prior_scale(ctx, param, value):
    text = str(value).strip().lower()
    if text == "auto":
        return "auto"
    try:
        f = float(text)
    except ValueError:
        f = float("nan")
    if not (f > 0 and f < float("inf")):
        raise click.BadParameter(f"expected 'auto' or a positive number, got {value!r}")
    return f


prior_scale_option = click.option(
    "--prior-scale",
    "prior_scale",
    default="1",
    show_default=True,
    metavar="auto|F",
    callback=_prior_scale,
    help="Multiply the SUM's SIGMA_VSO / SIGMA_PTG by F in the pose solve; 'auto': when the "
    "measurements contradict them (normalised change above its 99.9 % quantile), widen them by the "
    "estimated factor and solve again.",
)


def pose_options(sigma_px: float, no_prior: bool, min_landmarks: int, prior_scale=1.0, **more):
    """PoseOptions from --sigma-px, --no-prior, --min-landmarks and --prior-scale (a number or
    ``"auto"``), plus any other PoseOptions fields."""
    from spctool.stages.pose import PoseOptions

    scale = (
        {"prior_scale": 1.0, "estimate_prior_scale": True}
        if prior_scale == "auto"
        else {"prior_scale": float(prior_scale)}
    )
    return PoseOptions(
        sigma_px=sigma_px, use_prior=not no_prior, min_landmarks=min_landmarks, **scale, **more
    )


def weights_option(extra: str = ""):
    """--weights of the final pose solve (navigate, batch): calibrated (default), uniform or surface."""
    return click.option(
        "--weights",
        type=click.Choice(["calibrated", "uniform", "surface"]),
        default="calibrated",
        show_default=True,
        help="The final pose solve.  calibrated: uniform weights (1/sigma_px^2 per axis) and the "
        "covariance of that fit under each landmark's registration covariance plus the model error the "
        "residuals show, with as large a part common to the landmarks.  surface: weighted by the "
        "registration covariances and the shading model's error (every landmark registered again with "
        "the other photometric law and its maplet's heights smoothed once more; in image space also the "
        "other template shading and no cast shadows: the shifts enter as errors shared by the picture's "
        "landmarks): conservative, 40-90 % more time.  uniform: uniform weights and the formal "
        "covariance of sigma_px (the old way)." + extra,
    )


template_shading_option = click.option(
    "--template-shading",
    type=click.Choice(["smooth", "facet", "gouraud"]),
    default="smooth",
    show_default=True,
    help="Image space: template normals from interpolated node slopes (smooth) or flat triangles, "
    "two per maplet cell (facet), or the radiance shaded at the maplet's nodes and interpolated "
    "(gouraud, as maplet space predicts it; the Monte Carlo's image plan).",
)

photo_shadows_option = click.option(
    "--photo-shadows",
    type=click.Choice(["auto", "use"]),
    default="auto",
    show_default=True,
    help="Image space: auto leaves a landmark's photo pixels at the photo's dark level (read under the "
    "template's own shadows) out of its full-resolution correlation, since the maplet's smoothed heights "
    "cannot place those shadows' edges; use correlates them as dark.",
)

#: register --panels and correlate --panels: one PNG per landmark
panels_option = click.option(
    "--panels",
    "panels",
    type=click.Path(file_okay=False),
    default=None,
    metavar="DIR",
    help="Write DIR/LANDMARK_PICTURE_panel.png per landmark (correlate: ..._correlate-panel.png): "
    "predicted | extracted (image space: template | photo window) | correlation surface with the "
    "sub-pixel peak, enlarged, with the figures. A different picture already there is kept as .bak.",
)

#: register and navigate: workers over the landmarks (RegisterOptions.threads)
threads_option = click.option(
    "--threads",
    type=click.IntRange(min=1),
    default=None,
    metavar="N",
    help="Register the landmarks with N workers (s16 schedule; maplet space: processes forked from this "
    "one, image space: threads); 1 = one thread. The results do not depend on N.  [default: "
    "NUMBA_NUM_THREADS, else every core; maplet space two landmarks per worker at least and one "
    "process below 100,000 maplet cells in all]",
)
