"""Compiled kernels on first use: the one-line note, and ``spctool warmup``.

spctool's hot loops are numba kernels compiled on their first call and cached on disk (next to the
module, or in ``NUMBA_CACHE_DIR``).  On a fresh install the first command that needs them spends
20–30 s compiling with nothing else to show, so :func:`first_run_note` checks, before a command runs,
whether the kernels that command uses have a cached index file (numba's own cache locator says where)
and, when one is missing, arms one note on stderr that is printed when numba really starts compiling
(its ``numba:compile`` event).  A command that refuses its input before any kernel runs therefore
prints its one error line and nothing else.  ``spctool warmup`` compiles every kernel the
commands use by running the shipped demo through lithos-select, register (maplet and image space),
solve-pose, a small render and make-maplets, so that later commands start at once.
"""

from __future__ import annotations

import importlib
import sys
import tempfile
import time
from pathlib import Path

import click

from spctool.cli.common import Context, pass_context

#: sentinel kernels per family: (module, function); a family is warm when its kernels' cache index
#: files exist (kernels inlined into others have none and are not listed)
FAMILIES = {
    "camera": (("spctool.geometry.camera", "_k_project_body"),),
    "maplet": (
        ("spctool.geometry._heightkernels", "slopes"),
        ("spctool.stages.extract", "_brt0_kernel"),
        ("spctool.stages.correlate", "_k_ncc"),
    ),
    "rays": (("spctool.geometry._raykernels", "trace"), ("spctool.geometry._bvhkernels", "build_patch_tree")),
    "render": (("spctool.geometry._patchkernels", "_fused_rays"),),
}
_PIPELINE = ("camera", "maplet", "rays")
#: the kernel families each command needs (commands not listed compile nothing worth a note)
COMMAND_FAMILIES = {
    "lithos-select": ("camera", "rays"),
    "predict": ("camera", "maplet"),
    "extract": ("camera", "maplet"),
    "correlate": ("camera", "maplet"),
    "register": ("camera", "maplet"),
    "solve-pose": ("camera",),
    "project": ("camera", "rays"),
    "render": ("camera", "rays", "render"),
    "simulate": ("camera", "rays", "render"),
    "make-maplets": ("rays",),
    "demo": _PIPELINE,
    "batch": _PIPELINE,
    "montecarlo": ("camera", "maplet", "render"),
}
#: what the README quotes: a cold `spctool demo` compiles for about this long on one core
COMPILE_SECONDS = "30 s"


def _index_path(module: str, name: str) -> Path | None:
    func = getattr(importlib.import_module(module), name, None)
    cache = getattr(func, "_cache", None)
    cache_file = getattr(cache, "_cache_file", None)
    path = getattr(cache_file, "_index_path", None)
    return Path(path) if path else None


def cold_families(families) -> list[str]:
    """The kernel families (of :data:`FAMILIES`) with a kernel not yet in numba's on-disk cache."""
    cold = []
    for fam in families:
        for module, name in FAMILIES[fam]:
            try:
                path = _index_path(module, name)
            except Exception:  # an import problem surfaces in the command itself
                return []
            if path is not None and not path.exists():
                cold.append(fam)
                break
    return cold


def compile_bytecode(package: Path | None = None) -> tuple[int, str]:
    """Byte-compile spctool's own modules into their ``__pycache__`` (what pip does when it installs a
    wheel; an editable install, or a shell with PYTHONDONTWRITEBYTECODE set, otherwise compiles every
    module from source in every process: about 0.2 s of each command's start).  Modules whose
    bytecode is current are left alone.  Returns ``(modules compiled now, note)``: the note is empty,
    or says how many could not be written (a read-only install: the commands still run, from source)."""
    import compileall
    import importlib.util
    import io
    from contextlib import redirect_stdout

    if package is None:
        import spctool

        package = Path(spctool.__file__).parent
    sources = sorted(p for p in package.rglob("*.py") if "__pycache__" not in p.parts)

    def stamp(source):
        try:
            return Path(importlib.util.cache_from_source(str(source))).stat().st_mtime_ns
        except OSError:
            return None

    before = [stamp(p) for p in sources]
    failed = 0
    with redirect_stdout(io.StringIO()):  # compileall prints each file it could not write
        for p in sources:
            failed += not compileall.compile_file(str(p), quiet=1)
    done = sum(stamp(p) not in (None, b) for p, b in zip(sources, before))
    note = f"{failed} module(s) under {package} not byte-compiled (not writable?)" if failed else ""
    return done, note


def first_run_note(ctx: Context, command: str | None, args=None):
    """Arm one stderr note (silenced by -q), printed when ``command`` starts compiling kernels it
    has no cache for.  Returns the function that disarms it (call it when the command ends), or None
    when nothing was armed."""
    args = sys.argv[1:] if args is None else args
    if not command or command not in COMMAND_FAMILIES or ctx.verbosity < 0:
        return None
    if any(a in ("-h", "--help", "--example", "--copy-to") for a in args):
        return None
    cold = cold_families(COMMAND_FAMILIES[command])
    if not cold:
        return None
    from numba.core import event as numba_event  # numba only for commands with cold kernels

    class NoteOnCompile(numba_event.Listener):
        """Prints the note at the first ``numba:compile`` start (a cache miss), then stays quiet."""

        def on_start(self, event) -> None:
            ctx.note_once(message)  # once: note_once remembers it

        def on_end(self, event) -> None:
            pass

    message = (
        f"compiling spctool's numba kernels ({', '.join(cold)}) on first use: this run spends a few "
        f"seconds to {COMPILE_SECONDS} more, once (later runs load them from the cache; "
        "'spctool warmup' compiles them all now)"
    )
    listener = NoteOnCompile()
    numba_event.register("numba:compile", listener)

    def disarm() -> None:
        try:
            numba_event.unregister("numba:compile", listener)
        except ValueError:  # already gone
            pass

    return disarm


@click.command("warmup")
@pass_context
def warmup_cmd(ctx: Context):
    """Compile and cache every numba kernel now, so that later commands start at once.

    spctool's inner loops are compiled on their first use and cached on disk (next to the installed
    modules, or under NUMBA_CACHE_DIR); the first command after an install otherwise spends 20-30 s
    compiling.  warmup byte-compiles spctool's own modules (as pip does for a wheel: an editable
    install under PYTHONDONTWRITEBYTECODE otherwise compiles them from source in every command, about
    0.2 s), then runs the shipped demo working directory through lithos-select, register in
    maplet and in image space, solve-pose, a render of a small window and make-maplets, all in a
    temporary directory, and prints one line per step with its time.  Run it once after installing
    (or after upgrading spctool or numba).  Exit code 0, or 1 when a step failed.

    Example:

    \b
      spctool warmup
    """
    from spctool.batch import BatchOptions, navigate_picture
    from spctool.sim.demo import copy_demo
    from spctool.stages.register import RegisterOptions

    before = cold_families(FAMILIES)
    passed = []  # one bool per step
    with tempfile.TemporaryDirectory(prefix="spctool-warmup-") as tmp:
        root = copy_demo(Path(tmp) / "demo")
        pic = sorted(p.stem for p in (root / "SUMFILES").glob("*.SUM"))[0]

        def pipeline(space):
            opts = BatchOptions(register=RegisterOptions(space=space))
            navigate_picture(root, pic, opts)

        def render_window():
            from spctool.formats.sumfile import read_sum
            from spctool.formats.workdir import WorkDir
            from spctool.geometry.camera import Camera
            from spctool.stages.render import RenderOptions, render

            wd = WorkDir(root)
            p = read_sum(wd.sum_path(pic))
            cam = Camera.from_picture(p, wd.read_settings(None))
            c = int(p.npx) // 2
            name = wd.landmark_names()[0]
            render(
                cam,
                p.sz,
                wd.read_shape(None),
                [wd.read_maplet(name)],
                RenderOptions(),
                window=(c - 8, c + 8, c - 8, c + 8),
            )
            render(
                cam, p.sz, None, [wd.read_maplet(name)], RenderOptions(), window=(c - 8, c + 8, c - 8, c + 8)
            )

        def maplets():
            import numpy as np

            from spctool.formats.workdir import WorkDir
            from spctool.geometry.surfaces import ShapeSurface
            from spctool.sim.maplets import make_maplets

            wd = WorkDir(root)
            lmk = wd.read_landmark(wd.landmark_names()[0])
            make_maplets(
                ShapeSurface.from_model(wd.read_shape(None)), ["WARM01"], np.array([lmk.vlm]), lmk.scale, 4
            )

        def bytecode():
            done, note = compile_bytecode()
            return f"{done} module(s) compiled" + (f"; {note}" if note else "")

        for label, fn in (
            ("byte-compile spctool's modules", bytecode),
            ("lithos-select, register (maplet space), solve-pose", lambda: pipeline("maplet")),
            ("register (image space)", lambda: pipeline("image")),
            ("render", render_window),
            ("make-maplets", maplets),
        ):
            t0 = time.perf_counter()
            try:
                said = fn()
                ok, text = True, "ok" + (f" ({said})" if said else "")
            except Exception as exc:  # report and go on: warmup never leaves a traceback
                ok, text = False, f"failed: {type(exc).__name__}: {exc}"
            passed.append(ok)
            if ctx.verbosity >= 0:
                click.echo(f"spctool: warmup: {label}: {time.perf_counter() - t0:.1f} s {text}", err=True)
    after = cold_families(FAMILIES)
    click.echo(
        f"kernels compiled and cached: {', '.join(sorted(set(before) - set(after))) or 'none needed'}; "
        f"still cold: {', '.join(after) or 'none'}"
    )
    if not all(passed):
        raise click.exceptions.Exit(1)


def register(cli):
    cli.add_command(warmup_cmd)
