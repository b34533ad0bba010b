"""Progress and first-run feedback: render reports every line once (and the same pixels as without a
callback), the progress helper is silent when stderr is not a terminal or with -q, and the
first-use compile note appears exactly when a command's kernels are missing from numba's cache."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from click.testing import CliRunner
from test_render import _camera, sphere  # noqa: F401  (sphere is a fixture)

from spctool.cli import jit
from spctool.cli.common import Context, progress
from spctool.cli.main import cli
from spctool.stages.render import RenderOptions, render


def test_render_progress_counts_every_line_once(request):
    shape = request.getfixturevalue("sphere")
    cam = _camera([0.0, -4.0, 1.0], [0.0, 0.0, 0.0], npx=60, nln=50, k=10.0)
    opt = RenderOptions(supersample=2, chunk=600)  # 50 samples x 4 sub-rays: 3 lines per batch
    calls = []
    r = render(cam, [1.0, -0.5, 0.3], shape, [], opt, window=(5, 54, 3, 47), progress=calls.append)
    assert sum(calls) == 45 and calls == [3] * 15
    plain = render(cam, [1.0, -0.5, 0.3], shape, [], opt, window=(5, 54, 3, 47))
    np.testing.assert_array_equal(r.radiance, plain.radiance)


def test_progress_is_silent_off_a_terminal_and_with_quiet(capsys):
    for verbosity in (0, -1):
        with progress(Context(verbosity=verbosity), "work", 3) as advance:
            advance()
            advance(2, description="more work")
    out = capsys.readouterr()
    assert out.out == "" and out.err == ""


def test_first_run_note_only_when_the_command_kernels_are_cold(monkeypatch, tmp_path):
    cold = {"maplet"}
    monkeypatch.setattr(jit, "_index_path", lambda m, n: tmp_path / (n if jit_family(m, n) in cold else "x"))
    (tmp_path / "x").write_text("")

    def jit_family(module, name):
        return next(f for f, ks in jit.FAMILIES.items() if (module, name) in ks)

    assert jit.cold_families(["camera", "maplet", "rays"]) == ["maplet"]
    from numba.core import event

    said = []
    monkeypatch.setattr(Context, "note_once", lambda self, m: said.append(m))
    disarm = jit.first_run_note(Context(), "register", args=["register", "P1"])
    assert said == []  # armed, not said: a command that refuses its input first prints only its error
    with event.trigger_event("numba:compile"):  # numba starts compiling (a cache miss)
        pass
    disarm()
    with event.trigger_event("numba:compile"):  # disarmed when the command ends
        pass
    assert len(said) == 1 and "maplet" in said[0] and "spctool warmup" in said[0]
    for command, args, verbosity in (
        ("solve-pose", ["solve-pose", "P1"], 0),  # camera only: warm
        ("register", ["register", "--help"], 0),
        ("register", ["register", "P1"], -1),  # -q
        ("info", ["info", "X.SUM"], 0),
    ):
        assert jit.first_run_note(Context(verbosity=verbosity), command, args=args) is None
    with event.trigger_event("numba:compile"):
        pass
    assert len(said) == 1


def test_cold_kernels_leave_a_refused_input_with_one_stderr_line(monkeypatch, tmp_path):
    """CI's fuzz found it: a cold cache printed the compile note before simulate refused its spec."""
    monkeypatch.setattr(jit, "cold_families", lambda fams: list(fams))  # every kernel cold
    spec = tmp_path / "spec.toml"
    spec.write_text("seet = 1\n")
    res = CliRunner().invoke(cli, ["simulate", str(spec), str(tmp_path / "w")])
    assert res.exit_code == 2
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("spctool: error:") and "spec.toml" in lines[0], lines


def test_every_command_with_kernels_is_known_to_the_note():
    from spctool.cli.main import COMMANDS

    assert set(jit.COMMAND_FAMILIES) <= set(COMMANDS)
    for fams in jit.COMMAND_FAMILIES.values():
        assert set(fams) <= set(jit.FAMILIES)
    # the sentinels exist and are cached kernels with an index path
    for fam in jit.FAMILIES:
        for module, name in jit.FAMILIES[fam]:
            assert jit._index_path(module, name) is not None


def test_warmup_help_runs():
    res = CliRunner().invoke(cli, ["warmup", "--help"])
    assert res.exit_code == 0 and "Compile and cache" in res.output


def test_compile_bytecode_writes_what_is_stale_and_says_what_it_could_not(tmp_path, monkeypatch):
    import compileall
    import importlib.util
    import os

    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    for f in (pkg / "__init__.py", pkg / "a.py", pkg / "sub" / "b.py"):
        f.write_text("X = 1\n")
    assert jit.compile_bytecode(pkg) == (3, "")
    for f in (pkg / "a.py", pkg / "sub" / "b.py"):
        assert Path(importlib.util.cache_from_source(str(f))).is_file()
    assert jit.compile_bytecode(pkg) == (0, "")  # current: left alone
    src = pkg / "a.py"
    src.write_text("X = 2\n")
    st = src.stat()
    os.utime(src, ns=(st.st_atime_ns, st.st_mtime_ns + 5_000_000_000))  # edited later
    assert jit.compile_bytecode(pkg) == (1, "")
    monkeypatch.setattr(compileall, "compile_file", lambda *a, **k: False)  # e.g. a read-only install
    done, note = jit.compile_bytecode(pkg)
    assert done == 0 and note.startswith("3 module(s) under ") and str(pkg) in note


def test_compile_progress_shows_what_compiles_while_it_compiles(monkeypatch):
    """On a terminal the compilation is never silent: the status names the kernel compiling now (the
    innermost of spctool's), counts those done, and is cleared when the compilation ends."""
    import time
    import types

    from numba.core import event

    def compiling(module, name):
        k = types.SimpleNamespace(py_func=types.SimpleNamespace(__module__=module, __name__=name))
        return event.trigger_event("numba:compile", data={"dispatcher": k})

    shown = []
    cp = jit.CompileProgress(Context(), note="", live=True)
    monkeypatch.setattr(cp, "_show", shown.append)
    disarm = cp.arm()
    try:
        with compiling("spctool.stages.correlate", "_k_ncc"):
            with compiling("numba.misc.quicksort", "run"):
                time.sleep(0.65)
            with compiling("spctool.geometry._raykernels", "trace"):
                time.sleep(0.6)
    finally:
        disarm()
    texts = [t for t in shown if t]
    assert any("0 done, now correlate._k_ncc" in t for t in texts)  # numba's own kernels are not named
    assert any("now raykernels.trace" in t for t in texts)
    assert shown[-1] is None  # cleared at the end
    assert cp.done == {"correlate._k_ncc", "raykernels.trace"} and cp.depth == 0


def test_a_first_demo_compiles_registration_in_a_helper_on_a_terminal_or_not(monkeypatch):
    """demo and navigate select first and register after: with register's kernels cold and two cores,
    a second process compiles them meanwhile, on a terminal or not (it prints nothing) and with -q;
    never for other commands, when register's kernels are warm, or with SPCTOOL_NO_HELPER=1; the
    helper is ended with the command."""
    assert jit.start_helper("register", ["camera", "maplet", "rays"]) is None
    assert jit.start_helper("demo", ["camera", "rays"]) is None
    monkeypatch.setenv("SPCTOOL_NO_HELPER", "1")
    assert jit.start_helper("navigate", ["maplet", "rays"]) is None
    monkeypatch.delenv("SPCTOOL_NO_HELPER")
    monkeypatch.setattr("os.cpu_count", lambda: 2)
    helper = jit.start_helper("demo", ["camera", "maplet"])  # stderr is not a terminal here
    assert helper is not None and "precompile_kernels" in helper.args[-1]
    jit.stop_helper(helper)
    assert helper.poll() is not None

    # through first_run_note: -q silences the note, not the helper; other commands get none with -q
    started, said = [], []
    monkeypatch.setattr(jit, "cold_families", lambda fams: list(fams))  # every kernel cold
    monkeypatch.setattr(jit, "start_helper", lambda command, cold: started.append(command) or None)
    monkeypatch.setattr(Context, "note_once", lambda self, m: said.append(m))
    assert jit.first_run_note(Context(verbosity=-1), "demo", args=["-q", "demo"]) is None
    assert jit.first_run_note(Context(verbosity=-1), "register", args=["-q", "register", "P1"]) is None
    disarm = jit.first_run_note(Context(verbosity=0), "navigate", args=["navigate", "P1"])
    assert started == ["demo", "navigate"] and disarm is not None
    disarm()
    assert said == []  # nothing compiled


_HELPER_LIST_CHECK = """
import importlib, os, sys
from click.testing import CliRunner
from spctool.cli import jit
from spctool.cli.main import cli
from spctool.sim.demo import copy_demo

root = copy_demo(sys.argv[1])
for picture in ("P000000001A1", "P000000002A1", "P000000003A1", "P000000004A1"):
    res = CliRunner().invoke(cli, ["-q", "-C", str(root), "register", picture, "-o", os.devnull])
    assert res.exit_code == 0, res.output
for module, name, codes in jit.REGISTER_KERNELS:
    disp = getattr(importlib.import_module(module), name)
    assert disp.signatures == [jit.kernel_signature(codes)], (name, disp.signatures)
assert jit.precompile_kernels() == len(jit.REGISTER_KERNELS)
print("ok")
"""


def test_the_helper_compiles_what_register_uses_on_the_demo(tmp_path):
    """The helper's list is register's: after a register of the demo's pictures (maplet space) every listed
    kernel holds exactly the listed signature and no other one; precompile_kernels then only loads
    them (here they are compiled already).  In a process of its own: the kernels of this test process
    may hold other signatures from other tests (a uint16 photo, say)."""
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[1]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(root), os.environ.get("PYTHONPATH", "")])}
    res = subprocess.run(
        [sys.executable, "-c", _HELPER_LIST_CHECK, str(tmp_path / "demo")],
        capture_output=True, text=True, env=env, timeout=600,
    )  # fmt: skip
    assert res.returncode == 0 and res.stdout.strip() == "ok", res.stderr[-3000:]
