"""Compiled kernels on first use: the one-line note, and ``spctool warmup``.

spctool's hot loops are numba kernels compiled on their first call and cached on disk (next to the
module, or in ``NUMBA_CACHE_DIR``).  On a fresh install the first command that needs them spends
up to about 15 s of CPU compiling (a first ``spctool demo``), so :func:`first_run_note` checks, before a
command runs,
whether the kernels that command uses have a cached index file (numba's own cache locator says where)
and, when one is missing, arms one note on stderr that is printed when numba really starts compiling
(its ``numba:compile`` event).  A command that refuses its input before any kernel runs therefore
prints its one error line and nothing else; on a terminal :class:`CompileProgress` then shows, every
half second, which kernel compiles and how many are done.  ``spctool warmup`` compiles every kernel the
commands use by running the shipped demo through lithos-select, register (maplet and image space),
solve-pose, a small render and make-maplets, so that later commands start at once.  A first ``demo``
or ``navigate`` also starts a helper process that compiles register's kernels from the last to the
first (:data:`REGISTER_KERNELS`) while the command compiles them from the first: on two cores the
first demo then takes about the time of half the compilation.  The helper runs on a terminal or not
(a script, a pipe, CI) and with -q: it prints nothing, only the display needs the terminal.
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
    "camera": (("spctool.geometry._camerakernels", "_k_project_body"),),
    "maplet": (
        ("spctool.geometry._heightkernels", "slopes"),
        ("spctool.stages.extract", "_k_sample_nodes"),
        ("spctool.stages.correlate", "_k_front"),
    ),
    "rays": (("spctool.geometry._raykernels", "trace"), ("spctool.geometry._bvhkernels", "build_patch_tree")),
    "render": (("spctool.geometry._patchkernels", "_fused_rays"),),
    "heights": (("spctool.stages.photoclinometry", "_k_gauss_newton"),),
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
    "demo": ("camera", "maplet"),  # its occlusion tests trace a few rays each: numpy (geometry.shape)
    "navigate": _PIPELINE,
    "batch": _PIPELINE,
    "montecarlo": ("camera", "maplet", "render"),
    "lithos": ("camera", "maplet", "heights"),
}
#: a cold `spctool demo` compiles for about this long on one core (12.7 s of compilation, 15.0 s of CPU
#: in all, measured at load 4.4; docs/benchmarks.md)
COMPILE_SECONDS = "15 s"


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


class CompileProgress:
    """Shows numba compiling, while it does: on a terminal, a status (in the command's progress bar when
    one is on screen, else a line of its own) refreshed every half second with the kernels compiled so
    far, the one compiling now and the seconds spent, so that no stretch of compilation is silent;
    ``note`` (if any) is printed once, on stderr, at the first compilation (also when not a terminal).

    Only the process that armed it reports (a forked worker compiles silently), and its refresh thread
    runs only while a kernel compiles (a command forks its workers between compilations)."""

    def __init__(self, ctx: Context, note: str = "", live: bool | None = None):
        import os
        import threading

        self.ctx = ctx
        self.note = note
        self.live = (sys.stderr.isatty() and ctx.verbosity >= 0) if live is None else live
        self.pid = os.getpid()
        self.depth = 0
        self.done: set = set()
        self.stack: list = []  # the kernels compiling now, outermost first
        self.spent = 0.0  # seconds of finished compilation
        self.started = None  # perf_counter of the compilation under way
        self._stop = threading.Event()
        self._thread = None
        self._lock = threading.Lock()
        self._listener = None

    # the numba event listener ------------------------------------------------------------------
    def _on_start(self, event) -> None:
        import os

        if os.getpid() != self.pid:
            return
        name = _kernel_name((event.data or {}).get("dispatcher"))
        with self._lock:
            self.depth += 1
            if self.depth == 1:
                self.started = time.perf_counter()
                if self.note:
                    self.ctx.note_once(self.note)
                if self.live:
                    self._start_thread()
            self.stack.append(name)

    def _on_end(self, event) -> None:
        import os

        if os.getpid() != self.pid:
            return
        name = _kernel_name((event.data or {}).get("dispatcher"))
        stop = False
        with self._lock:
            self.depth = max(0, self.depth - 1)
            if self.stack:
                self.stack.pop()
            if name:
                self.done.add(name)
            if self.depth == 0 and self.started is not None:
                self.spent += time.perf_counter() - self.started
                self.started = None
                stop = True
        if stop:
            self._stop_thread()

    # the display ---------------------------------------------------------------------------------
    def text(self) -> str:
        elapsed = self.spent + (time.perf_counter() - self.started if self.started is not None else 0.0)
        current = next((n for n in reversed(self.stack) if n), "")
        now = f", now {current}" if self.started is not None and current else ""
        return f"compiling kernels (once): {len(self.done)} done{now}, {elapsed:.0f} s"

    def _show(self, text: str | None) -> None:
        from spctool.cli.common import ACTIVE_BARS

        if ACTIVE_BARS:
            ACTIVE_BARS[-1](text)
        elif text:
            sys.stderr.write("\r\x1b[Kspctool: " + text[: max(20, _columns() - 10)])
            sys.stderr.flush()
        else:
            sys.stderr.write("\r\x1b[K")
            sys.stderr.flush()

    def _start_thread(self) -> None:
        import threading

        self._stop.clear()

        def tick():
            while not self._stop.wait(0.5):
                self._show(self.text())

        self._thread = threading.Thread(target=tick, name="spctool-compile-progress", daemon=True)
        self._thread.start()

    def _stop_thread(self) -> None:
        thread, self._thread = self._thread, None
        if thread is not None:
            self._stop.set()
            thread.join()
            self._show(None)

    # arm / disarm --------------------------------------------------------------------------------
    def arm(self):
        """Listen to numba's compilations; returns the function that stops listening."""
        from numba.core import event as numba_event

        owner = self

        class Listener(numba_event.Listener):
            def on_start(self, event) -> None:
                owner._on_start(event)

            def on_end(self, event) -> None:
                owner._on_end(event)

        self._listener = Listener()
        numba_event.register("numba:compile", self._listener)

        def disarm() -> None:
            try:
                numba_event.unregister("numba:compile", self._listener)
            except ValueError:  # already gone
                pass
            self._stop_thread()

        return disarm


def _kernel_name(dispatcher) -> str:
    """'module.function' of one of spctool's kernels, short ('correlate._k_ncc'); '' for numba's own."""
    func = getattr(dispatcher, "py_func", None)
    module = getattr(func, "__module__", "") or ""
    if not module.startswith("spctool."):
        return ""
    return f"{module.rsplit('.', 1)[-1].lstrip('_')}.{func.__name__}"


def _columns() -> int:
    import shutil

    return shutil.get_terminal_size((80, 20)).columns


def first_run_note(ctx: Context, command: str | None, args=None):
    """Arm, for a command whose kernels are not all in numba's cache, one stderr note (silenced by -q)
    printed when it really starts compiling, and the live :class:`CompileProgress` on a terminal; for
    a :data:`HELPED` command, also with -q and off a terminal, the helper process
    (:func:`start_helper`).  Returns the function that disarms them (call it when the command ends),
    or None when nothing was armed."""
    args = sys.argv[1:] if args is None else args
    if not command or command not in COMMAND_FAMILIES:
        return None
    if ctx.verbosity < 0 and command not in HELPED:
        return None
    if any(a in ("-h", "--help", "--example", "--copy-to") for a in args):
        return None
    cold = cold_families(COMMAND_FAMILIES[command])
    if not cold:
        return None
    disarm = None
    if ctx.verbosity >= 0:
        message = (
            f"compiling spctool's numba kernels ({', '.join(cold)}) on first use: this run spends a few "
            f"seconds to {COMPILE_SECONDS} more, once (later runs load them from the cache; "
            "'spctool warmup' compiles them all now)"
        )
        disarm = CompileProgress(ctx, message).arm()
    helper = start_helper(command, cold)
    if helper is None:
        return disarm

    def disarm_both() -> None:
        if disarm is not None:
            disarm()
        stop_helper(helper)

    return disarm_both


#: commands that run lithos-select first and register after, in one process: on a first run a second
#: process compiles register's kernels meanwhile
HELPED = ("demo", "navigate")

#: register's top-level kernels (maplet space) in the order a first register compiles them, each with
#: the argument types its call site gives it (one signature each; kernels they call compile with
#: them).  Codes: f/i/? a float64/int64/boolean scalar; fN, iN, bN, u1 a C-contiguous N-d float64,
#: int64, bool, uint8 array, ``r`` read-only; FN a tuple of N float64.  tests/test_progress.py checks
#: that a register on the demo uses exactly these.
REGISTER_KERNELS = (
    ("spctool.geometry._camerakernels", "_k_invert", "f1 f1 F34 i F5 f i f2r f1 f1 f2 i1"),
    ("spctool.stages.extract", "_k_node_positions", "f2 f f f1 f1 f1 f1 f3"),
    ("spctool.geometry._camerakernels", "_k_project_body", "f2 f2r f1r F34 i f1 f1 b1"),
    ("spctool.geometry._heightkernels", "slopes", "f2 b2 f2 f2 b2"),
    ("spctool.geometry._camerakernels", "_k_jac_camera", "f2 F34 i f1 f1 f3"),
    ("spctool.stages.extract", "_k_sample_nodes", "f2 f2 f2 b2 b2 ? ? f f f f f b2 b2 f2 b2"),
    ("spctool.stages.extract", "_k_shadow_offsets", "f f i i ? ? i"),
    ("spctool.stages.extract", "_enhance_kernel", "b2 i2 i2 b2 b2"),
    ("spctool.geometry._heightkernels", "surface_cosines", "f2 f2 f f f f2 ? f2"),
    ("spctool.geometry._heightkernels", "march_blocked", "f2 b2 b2 f f f f b2"),
    ("spctool.stages.extract", "_k_recentred", "f2 f2 f2 f f f f f ? i2 i2 ? b2 f2 f2 f2 b2 b2 b2 b2"),
    ("spctool.stages.correlate", "_k_front", "f2 b2 f2 b2 ? f i i i i i f i f ?"),
    ("spctool.stages.alignment", "_k_alignment", "f2 b2 f2 b2 i i i i i i f2 f1"),
    ("spctool.stages.extract", "_subsample_kernel", "f2 f1r f1r b1 f1r f1r f1r f1r f1 f f f f1 b1"),
)


def kernel_signature(codes: str) -> tuple:
    """The numba argument types of a :data:`REGISTER_KERNELS` signature."""
    from numba.core import types

    scalars = {"f": types.float64, "i": types.int64, "?": types.boolean}
    dtypes = {"f": types.float64, "i": types.int64, "b": types.boolean, "u": types.uint8}
    out = []
    for code in codes.split():
        if code in scalars:
            out.append(scalars[code])
        elif code[0] == "F":
            out.append(types.UniTuple(types.float64, int(code[1:])))
        else:
            ndim = int(code[1:].rstrip("r"))
            out.append(types.Array(dtypes[code[0]], ndim, "C", readonly=code.endswith("r")))
    return tuple(out)


def precompile_kernels(kernels=REGISTER_KERNELS, *, reverse: bool = True) -> int:
    """Compile (or load from numba's cache) ``kernels`` for their signatures, last first by default:
    the helper's work.  The command compiles them first to last as it reaches them, so the two meet
    in the middle (a kernel the helper has cached is loaded, not compiled again; numba writes its
    cache files whole and renames them).  Returns how many were compiled or loaded."""
    done = 0
    for module, name, codes in reversed(kernels) if reverse else kernels:
        getattr(importlib.import_module(module), name).compile(kernel_signature(codes))
        done += 1
    return done


def start_helper(command: str, cold):
    """For a :data:`HELPED` command whose registration kernels are cold, on a machine of two cores or
    more, start a second Python process that compiles them (:func:`precompile_kernels`, last first)
    while this one reads, selects and compiles them first to last.  On a terminal or not, with -q or
    not: the helper prints nothing (its output goes nowhere), it only fills numba's cache, so a first
    demo run by a script, a pipe or CI gains as much as one on a terminal.  Returns the process, or
    None."""
    import os
    import subprocess

    if command not in HELPED or "maplet" not in cold:
        return None
    if (os.cpu_count() or 1) < 2 or os.environ.get("SPCTOOL_NO_HELPER") == "1":
        return None
    code = "from spctool.cli.jit import precompile_kernels; precompile_kernels()"
    try:
        return subprocess.Popen(
            [sys.executable, "-c", code],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
    except OSError:  # no helper: this process compiles everything itself, as before
        return None


def stop_helper(helper) -> None:
    """End the helper if it still runs (the command is over; what it compiled so far is cached)."""
    if helper.poll() is None:
        helper.terminate()
        try:
            helper.wait(timeout=5)
        except Exception:
            helper.kill()


@click.command("warmup")
@pass_context
def warmup_cmd(ctx: Context):
    """Compile and cache every numba kernel now, so that later commands start at once.

    spctool's inner loops are compiled on their first use and cached on disk (next to the installed
    modules, or under NUMBA_CACHE_DIR); the first command after an install otherwise spends up to
    about 15 s compiling.  warmup byte-compiles spctool's own modules (as pip does for a wheel: an editable
    install under PYTHONDONTWRITEBYTECODE otherwise compiles them from source in every command, about
    0.2 s), then runs the shipped demo working directory through lithos-select, register in
    maplet and in image space, solve-pose, a render of a small window, make-maplets and lithos's
    per-cell solve, all in a temporary directory, and prints one line per step with its time (on a
    terminal, while a step compiles, which kernel compiles and how many are done).  Run it once after
    installing (or after upgrading spctool or numba).  Exit code 0, or 1 when a step failed.

    Example:

    \b
      spctool warmup
    """
    from spctool.batch import BatchOptions, navigate_picture
    from spctool.sim.demo import copy_demo
    from spctool.stages.register import RegisterOptions

    before = cold_families(FAMILIES)
    passed = []  # one bool per step
    disarm = CompileProgress(ctx).arm()  # on a terminal: what compiles now, live
    ctx_close = click.get_current_context().call_on_close
    ctx_close(disarm)
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

        def heights():
            import numpy as np

            from spctool.stages import photoclinometry as pc

            n = 5
            sun = np.array([[0.5, 0.0, 0.8], [0.0, 0.5, 0.8], [-0.5, 0.0, 0.8]])
            pics = pc.Pictures(np.ones((3, n, n)), np.ones((3, n, n), bool), sun, sun, np.zeros(3))
            pc.solve_cells(np.zeros((n, n)), np.zeros((n, n)), np.ones((n, n)), pics, np.ones(3))

        def bytecode():
            done, note = compile_bytecode()
            return f"{done} module(s) compiled" + (f"; {note}" if note else "")

        for label, fn in (
            ("byte-compile spctool's modules", bytecode),
            ("lithos-select, register (maplet space), solve-pose", lambda: pipeline("maplet")),
            ("register (image space)", lambda: pipeline("image")),
            ("render", render_window),
            ("make-maplets", maplets),
            ("lithos (per-cell solve)", heights),
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
