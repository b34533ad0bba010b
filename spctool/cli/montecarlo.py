"""``montecarlo``: S16's landmark-matching characterisation (Table 2 perturbations → Table 3 statistics).

A thin command over :mod:`spctool.sim.montecarlo`: build or load the scene (the ``s16-50m`` preset, a
saved ``--scene`` file, or a working directory made by ``spctool simulate``), run the study with a
progress bar, print the Table 3 report (text or ``--json``) and optionally write the PNG figures and a
per-sample CSV.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import click

from spctool.cli import options
from spctool.cli.common import Context, emit, pass_context, progress
from spctool.errors import SpcResultError, SpcUsageError

_HELP = """Characterise landmark registration by Monte Carlo (S16 Tables 2 and 3, Fig. 8).

S16 is Shoemaker et al. 2016, "Performance Characterization of a Landmark Measurement System for
ARRM Terrain Relative Navigation" (README, References).

One truth photo; for every landmark and sample the knowledge is perturbed with S16 Table 2's 1-sigma
errors -- spacecraft position (0.1667 m per axis) and attitude (0.05 deg per axis), landmark position
(3.33 cm per axis), maplet heights (3.33 mm) and albedo (0.047), pixel skew K_yx (1e-5), principal point
(0.1667 px), focal length (0.004 mm), OWEN distortion (1e-5, 1e-7, 1e-5, 1e-5, 0, 0) and Sun right
ascension/declination (0.3 deg) -- the landmark is registered in the unchanged photo and the error truth
- measured is recorded, truth being the projection of the true landmark with the true camera. Maplet
space runs S16's schedule (L = 10 ... 1, search +-5L cells, acceptance rho >= 0.3, no pose update,
linearised extraction) plus --refine steps at L = 1, its first step searching --acquire-reach cells
on the photo resampled beyond the maplet's edge (S16's search within the maplet ends near +-50
cells, 2.8 sigma of the a-priori pixel); image space (the direction of the Retina system,
Wright et al. 2016) searches at L = 4, 2, 1 over +-48 px with one rendered template, then re-renders it
at the estimate for --refine steps at L = 1; its templates have 2 x 2 rays per pixel, no cast
shadows and the radiance interpolated from the maplet's nodes (--template-shading gouraud, as maplet
space predicts it), and its converged stage fits the template on the photo
(--converge-peak gradient-photo): the study's height error on every maplet node makes the template
the noisier image and casts shadows the terrain does not have. Scalar perturbations are
Latin-Hypercube sampled per landmark (--sampling lhs, S16) or plain Monte Carlo (--sampling mc);
heights and albedo get an error on every maplet node (--fields cell, the default: its mean max rho,
about 0.5, is close to S16's 0.54-0.59, where one bias per maplet, --fields bias, gives about 0.93).

The report has S16 Table 3's layout (means and 1-sigma of the sample/line errors over the
successful samples, not found, below threshold, success rate, mean max rho) per landmark and for
all samples, S16's own table beside it, the checks against S16 and the image-space targets, and
the linear sensitivity of the errors to each perturbation. Each landmark is also registered once
with every sigma at zero: that floor (the scene's model error, which no estimator removes) is shown
beside its bias, with the excess |mean - floor| per axis (+- the mean's sigma/sqrt(n)), and each
landmark gets PASS or MISS against the per-landmark targets -- excess <= 0.01 px, 1 sigma <= 0.04
px per axis, success >= 99.5 % -- with the worst landmark named per target. --json writes the same
as one document (per landmark: floor, excess, targets, verdict; overall: worst_landmarks).

Scenes: --preset s16-50m builds S16's camera (Table 1) at 50 m over twelve 99x99 maplets of 1 cm
named as in S16 Fig. 6, with 3.33 mm truth terrain rendered (cast shadows, detector noise) by the
simulate machinery (about a minute); --scene FILE keeps that scene: read FILE when it exists,
else build the scene and save it there. Without --preset/--scene the working directory (-C) must
come from 'spctool simulate' (TRUTH.json); PICTURE defaults to its first picture.

A sample depends only on (--seed, landmark, sample index): results are identical bit for bit
whatever --jobs.

Examples:

\b
  spctool montecarlo --preset s16-50m --scene s16.npz --samples 20 --figures figs
  spctool montecarlo --preset s16-50m --scene s16.npz --samples 20 --space image --json > image.json
  spctool montecarlo --preset s16-50m --scene s16.npz --samples 20 --only position,attitude --sigma-scale 2
  spctool -C demo montecarlo P000000001A1 --samples 20
  spctool -C demo montecarlo P000000001A1 --samples 5 --space image --supersample 1 --template-slopes fourth
"""


def _names(text: str | None) -> list[str]:
    if not text:
        return []
    return [t.strip() for t in text.split(",") if t.strip()]


@click.command(
    "montecarlo",
    help=_HELP,
    short_help="Monte Carlo of landmark registration (Shoemaker et al. 2016, Table 3).",
)
@click.argument("picture", required=False)
@click.option(
    "--preset",
    type=click.Choice(["s16-50m"]),
    default=None,
    help="The built-in scene: the camera of Shoemaker et al. 2016 at 50 m, 12 landmarks, 99x99 "
    "maplets of 1 cm.",
)
@click.option(
    "--scene",
    "scene_path",
    metavar="FILE",
    type=click.Path(dir_okay=False),
    help="Scene cache (.npz): read it when it exists, else build the scene (--preset or -C) and save it.",
)
@click.option(
    "--world-seed",
    type=click.IntRange(min=0),
    default=16,
    show_default=True,
    metavar="N",
    help="Seed of the preset's world (terrain, noise).",
)
@click.option(
    "-l",
    "--landmarks",
    "landmarks",
    metavar="NAMES",
    help="Comma-separated landmarks to study (default: all of the scene).",
)
@options.space_option
@click.option(
    "--samples",
    type=click.IntRange(min=1),
    default=500,
    show_default=True,
    metavar="N",
    help="Samples per landmark (Shoemaker et al. 2016: 500).",
)
@click.option(
    "--seed",
    type=click.IntRange(min=0),
    default=0,
    show_default=True,
    metavar="N",
    help="Seed of every perturbation draw (recorded in the report).",
)
@click.option(
    "--sampling",
    type=click.Choice(["lhs", "mc"]),
    default="lhs",
    show_default=True,
    help="Latin Hypercube (as Shoemaker et al. 2016) or plain Monte Carlo.",
)
@click.option(
    "--fields",
    type=click.Choice(["cell", "bias"]),
    default="cell",
    show_default=True,
    help="Height/albedo errors: i.i.d. on every maplet node, or one bias per maplet.",
)
@click.option(
    "--only",
    "only",
    metavar="PARAMS",
    help="Perturb only these (comma-separated): position, attitude, landmark, height, albedo, "
    "skew, center, focal, distortion, sun.",
)
@click.option("--without", "without", metavar="PARAMS", help="Do not perturb these (comma-separated).")
@click.option(
    "--sigma-scale",
    type=options.FiniteFloatRange(min=0.0),
    default=1.0,
    show_default=True,
    metavar="F",
    help="Multiply every Table 2 sigma by F (success versus perturbation size).",
)
@click.option(
    "--refine",
    type=click.IntRange(min=0),
    default=1,
    show_default=True,
    metavar="N",
    help="Refinement steps at L = 1 that re-extract (maplet) or re-render (image) at the current "
    "estimate, before register's converged stage (least-squares alignment until the estimate "
    "moves < --converge-tol); maplet space with 0 is the schedule of Shoemaker et al. 2016 followed "
    "by that stage.",
)
@options.first_phases_option(
    "Correlate each landmark's first step at P x P half-bin phases and keep the best (default: 1).",
    default=None,
)
@options.acquire_reach_option(
    "Maplet space: the first step (L = 10) searches +-CELLS on the photo resampled onto the "
    "maplet's grid extended beyond its edge, so every offset compares the whole prediction "
    "(default: 72 x --sigma-scale, 4 sigma of the a-priori pixel; 0 with --refine 0 and "
    "--first-phases 1 is the schedule of Shoemaker et al. 2016).",
    default=None,
)
@click.option(
    "--supersample",
    type=click.IntRange(1, 4),
    default=None,
    metavar="N",
    help="Image space: N x N rays per pixel of the templates at L = 1 (default: 2 in the fine phase, "
    "as register, with one-ray drafts until the converged stage is near, and 1 in the coarse phase, "
    "which only acquires; N sets both phases: 1 takes about half the time, and on the s16-50m preset "
    "its worst landmark's 1 sigma is about 0.042 px instead of 0.037).",
)
@click.option(
    "--image-shadows/--no-image-shadows",
    "image_shadows",
    default=None,
    help="Image space: correlate the template's cast shadows as dark (register's default) or "
    "leave shadowed pixels out (the default here: the study's height error on every maplet node "
    "casts shadows the terrain does not have; on the s16-50m preset they moved the worst "
    "landmark's mean 0.02 px from its zero-perturbation floor).",
)
@click.option(
    "--template-slopes",
    type=click.Choice(["spc", "fourth"]),
    default=None,
    help="Image space: the node slopes the templates' shading interpolates: SPC's central "
    "differences (the default, as register) or the fourth-order central difference, which keeps "
    "more of the maplet's cell-scale relief (on the s16-50m preset the worst landmark's "
    "zero-perturbation floor is 0.064 px instead of 0.072) but amplifies the study's height "
    "noise (worst 1 sigma 0.040-0.043 px instead of 0.037).",
)
@click.option(
    "--template-shading",
    type=click.Choice(["gouraud", "smooth", "facet"]),
    default=None,
    help="Image space: the templates' shading. gouraud (the default here) computes the radiance "
    "at the maplet's nodes, as maplet space predicts it, and interpolates it; smooth (register's "
    "default) interpolates the node slopes and shades those; facet shades flat triangles. On the "
    "s16-50m preset the worst landmark's zero-perturbation floor is 0.064 px with gouraud and "
    "0.072 with smooth; facet loses most samples to the study's height noise.",
)
@click.option(
    "--converge-tol",
    type=options.FiniteFloatRange(min=0.0, min_open=True),
    default=None,
    metavar="PX",
    help="The converged stage stops when a step moves the estimate by less than PX (default: "
    "register's 0.005 in maplet space; 0.01 in image space, whose every step re-renders the "
    "template: on the s16-50m preset the same figures as 0.005, each sample within 0.013 px of "
    "it in 99 % of cases, for about 15 % less time).",
)
@click.option(
    "--converge-peak",
    type=click.Choice(["gradient", "gradient-photo", "gradient-symmetric", "gradient-weighted"]),
    default=None,
    help="The converged stage's least-squares alignment: 'gradient' fits the photo on the "
    "prediction and its gradient (register's default), 'gradient-photo' the prediction on the "
    "photo and its gradient (default in maplet space: the study's maplets, with a height error "
    "on every node, make the prediction the noisier image, and noise in the regressors biases a "
    "fit: on the s16-50m preset the worst landmark's mean moved 0.040 px from its "
    "zero-perturbation floor with 'gradient'). 'gradient-symmetric' regresses the difference on "
    "the mean of both images' gradients, 'gradient-weighted' on their mix weighted by each "
    "image's estimated noise (measured, not adopted: docs/benchmarks.md). Image space: "
    "'gradient-photo' too (the template shaded from the noisy heights).",
)
@click.option(
    "--jobs",
    "-j",
    type=click.IntRange(min=1),
    default=None,
    metavar="N",
    help="Worker processes (default: the CPUs available).",
)
@click.option(
    "--figures",
    "figures_dir",
    metavar="DIR",
    type=click.Path(file_okay=False),
    help="Write montecarlo_scatter.png (Shoemaker et al. 2016, Fig. 8), montecarlo_histograms.png and "
    "montecarlo_success.png (success versus a-priori pixel error) to DIR.",
)
@click.option(
    "--samples-csv",
    "samples_csv",
    metavar="FILE",
    type=click.Path(dir_okay=False),
    help="Write one CSV row per sample (status, rho, a-priori, measured, error, design).",
)
@click.option(
    "--check",
    is_flag=True,
    help="Exit 1 unless the results meet the targets: image space, over all samples, success "
    ">= 99.5 %, |mean| <= 0.05 px and 1 sigma <= 0.08 px per axis; maplet space at least as good "
    "as Shoemaker et al. 2016, Table 3 (overall success, worst landmark's |mean| and 1 sigma per axis).",
)
@options.json_option
@options.output_option
@pass_context
def montecarlo_cmd(
    ctx: Context,
    picture,
    preset,
    scene_path,
    world_seed,
    landmarks,
    space,
    samples,
    seed,
    sampling,
    fields,
    only,
    without,
    sigma_scale,
    refine,
    first_phases,
    acquire_reach,
    supersample,
    image_shadows,
    template_slopes,
    template_shading,
    converge_tol,
    converge_peak,
    jobs,
    figures_dir,
    samples_csv,
    check,
    as_json,
    output,
):
    from spctool.sim import montecarlo as mc
    from spctool.sim import montecarlo_report as mcr
    from spctool.sim import montecarlo_scene as mcs

    config = _config(
        mc, space, samples, seed, sampling, fields, only, without, sigma_scale, refine, first_phases,
        acquire_reach, supersample, image_shadows, template_slopes, template_shading, converge_tol,
        converge_peak,
    )  # fmt: skip
    t0 = time.perf_counter()
    scene = _load_scene(ctx, mcs, preset, scene_path, world_seed, picture)
    scene_s = time.perf_counter() - t0
    if landmarks:
        scene = scene.subset(_names(landmarks))
    total = len(scene) * samples
    ctx.info(f"{len(scene)} landmarks x {samples} samples, {space} space, {jobs or mc.default_jobs()} job(s)")
    # no refresh thread: the workers fork only from a single-threaded process (spctool.workers)
    with progress(ctx, f"montecarlo {space}", total, threaded=False) as advance:
        result = mc.run(scene, config, jobs=jobs or mc.default_jobs(), progress=advance)
    result.timing["scene_s"] = scene_s
    summary = mcr.summarise(result)
    if as_json:
        emit(json.dumps(mcr.report_document(result, summary), indent=1) + "\n", output)
    else:
        emit(mcr.format_report(result, summary), output)
    if figures_dir:
        for path in mcr.write_figures(result, figures_dir):
            ctx.info(f"wrote {path}")
    if samples_csv:
        mcr.write_samples_csv(result, samples_csv)
        ctx.info(f"wrote {samples_csv}")
    if check:
        group = "image_targets" if space == "image" else "s16_table3"
        failed = [k for k, v in summary["checks"].get(group, {}).items() if not v]
        if failed or not summary["checks"]:
            raise SpcResultError(f"montecarlo check ({group}) failed: {', '.join(failed) or 'no landmarks'}")


def _config(
    mc, space, samples, seed, sampling, fields, only, without, sigma_scale, refine, first_phases,
    acquire_reach, supersample, image_shadows, template_slopes, template_shading, converge_tol,
    converge_peak,
):  # fmt: skip
    """The study's :class:`spctool.sim.montecarlo.MonteCarloConfig` from the command's options (the
    perturbations kept, the space's plan with the options that change it); a template option with
    maplet space, or an unknown perturbation, is refused."""
    params = _names(only) or [p.name for p in mc.PARAMETERS]
    drop = set(_names(without))
    known = {p.name for p in mc.PARAMETERS}
    bad = [p for p in list(params) + list(drop) if p not in known]
    if bad:
        raise SpcUsageError(f"unknown perturbation {', '.join(bad)} (known: {', '.join(sorted(known))})")
    params = [p for p in params if p not in drop]
    if supersample is not None and space != "image":
        raise SpcUsageError("--supersample sets the image-space templates' rays: use it with --space image")
    templates = (image_shadows, template_slopes, template_shading)
    if any(t is not None for t in templates) and space != "image":
        raise SpcUsageError(
            "--image-shadows/--no-image-shadows, --template-slopes and --template-shading set the "
            "image-space templates: use them with --space image"
        )
    changes = {} if supersample is None else {"supersample": supersample}
    if image_shadows is not None:
        changes["image_shadows"] = image_shadows
    if template_slopes is not None:
        changes["template_slopes"] = template_slopes
    if template_shading is not None:
        changes["template_shading"] = template_shading
    if converge_tol is not None:
        changes["converge_tol"] = converge_tol
    if converge_peak is not None:
        changes["converge_peak"] = converge_peak
    return mc.MonteCarloConfig(
        samples=samples,
        seed=seed,
        sampling=sampling,
        fields=fields,
        parameters=tuple(params),
        sigma_scale=sigma_scale,
        space=space,
        plan=mc.default_plan(
            space,
            refine=refine,
            first_phases=first_phases,
            acquire_reach=mc.acquire_reach_for(sigma_scale) if acquire_reach is None else acquire_reach,
            **changes,
        ),
    )


def register(cli: click.Group) -> None:
    cli.add_command(montecarlo_cmd)


def _load_scene(ctx: Context, mcs, preset, scene_path, world_seed, picture):
    if scene_path and Path(scene_path).is_file():
        ctx.info(f"reading scene {scene_path}")
        scene = mcs.load_scene(scene_path)
        if preset and scene.info.get("preset") != preset:
            raise SpcUsageError(
                f"{scene_path}: holds {scene.info.get('preset') or 'a working-directory'} scene, "
                f"not preset {preset}"
            )
        if preset and scene.info.get("world_seed") != world_seed:
            raise SpcUsageError(f"{scene_path}: world seed {scene.info.get('world_seed')}, not {world_seed}")
        return scene
    if preset:
        if picture:
            raise SpcUsageError("a preset has its own picture: drop PICTURE")
        ctx.note_once(f"building the {preset} scene (about a minute; --scene FILE keeps it)")
        # the builder names each step as it starts: 3 world steps, then one render per landmark
        with progress(ctx, f"building {preset}", 3 + len(mcs.S16_LANDMARKS)) as advance:
            started = []

            def step(msg):
                ctx.info(msg, 2)
                advance(1 if started else 0, description=f"{preset}: {msg}")
                started.append(msg)

            scene = mcs.s16_scene(world_seed, progress=step)
    else:
        if not (Path(ctx.workdir) / "TRUTH.json").is_file():
            raise SpcUsageError(
                f"{ctx.workdir}: no TRUTH.json; give --preset s16-50m, --scene FILE, or -C a world made by "
                "'spctool simulate'"
            )
        scene = mcs.scene_from_workdir(str(Path(ctx.workdir).resolve()), picture)  # -C: cwd is DIR
    if scene_path:
        mcs.save_scene(scene, scene_path)
        ctx.info(f"saved scene {scene_path}")
    return scene
