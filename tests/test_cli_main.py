"""The command group: the static command table matches what the command modules register, and a
command imports only its own module (``spctool --version`` and ``spctool info`` never load numba), and
importing the command line keeps OpenBLAS to one thread unless the environment says otherwise."""

from __future__ import annotations

import importlib
import json
import subprocess
import sys

import click
import numpy as np
from click.testing import CliRunner

from spctool.cli.main import COMMAND_MODULES, COMMANDS, cli


def test_command_table_matches_the_modules():
    registered = {}
    for module in COMMAND_MODULES:
        group = click.Group()
        importlib.import_module(module).register(group)
        for name in group.commands:
            registered[name] = module
    assert registered == COMMANDS


def test_every_command_resolves_and_has_help_with_an_example():
    runner = CliRunner()
    listed = cli.list_commands(click.Context(cli))
    assert listed == list(COMMANDS)
    for name in listed:
        result = runner.invoke(cli, [name, "--help"])
        assert result.exit_code == 0, (name, result.output)
        assert "Example" in result.output, name
    bad = runner.invoke(cli, ["no-such-command"])
    assert bad.exit_code == 2 and "no-such-command" in bad.output


_PROBE = """
import json, sys
from spctool.cli.main import cli
try:
    cli.main(sys.argv[1:], standalone_mode=False)
except SystemExit:
    pass
heavy = ("numba", "scipy", "astropy", "spctool.stages.register", "spctool.sim.simulate")
print(json.dumps([m for m in heavy if m in sys.modules]))
"""


def _loaded(*args) -> list[str]:
    run = subprocess.run([sys.executable, "-c", _PROBE, *args], capture_output=True, text=True, check=True)
    return json.loads(run.stdout.strip().splitlines()[-1])


def test_commands_import_only_what_they_need(tmp_path):
    assert _loaded("--version") == []
    assert _loaded("--help") == []  # the command modules are light: the numerics load when a command runs
    sum_file = tmp_path / "X.SUM"
    sum_file.write_text("not a sum file\n")
    assert "numba" not in _loaded("info", str(sum_file))


_BLAS_PROBE = """
import os, sys
import spctool.cli.main
print("numpy" in sys.modules, os.environ.get("OPENBLAS_NUM_THREADS"))
"""


def test_the_command_line_keeps_openblas_to_one_thread_unless_told():
    """Importing the CLI sets OPENBLAS_NUM_THREADS=1 before numpy (and its OpenBLAS) can load, and leaves a
    value the user set alone (spctool.cli's docstring: the pool only spun, ~0.3 s CPU per command)."""
    import os

    def probe(env):
        run = subprocess.run([sys.executable, "-c", _BLAS_PROBE], capture_output=True, text=True, env=env)
        return run.stdout.split()

    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    assert probe(env) == ["False", "1"]
    assert probe({**env, "OPENBLAS_NUM_THREADS": "4"}) == ["False", "4"]


def test_a_global_option_after_the_command_gets_a_hint():
    """-q/-v/-C/--debug after a subcommand: the one error line says they are global and where they go."""
    run = CliRunner().invoke
    r = run(cli, ["info", "-q", "x.SUM"])
    assert r.exit_code == 2
    assert "-q is a global option: put it before the command, 'spctool -q info ...'" in r.stderr
    r = run(cli, ["info", "--verbose", "x.SUM"])
    assert "--verbose is a global option" in r.stderr
    r = run(cli, ["info", "--no-such", "x.SUM"])
    assert r.exit_code == 2 and "global option" not in r.stderr and "info --help'" in r.stderr


_CFFI_PROBE = """
import sys
import spctool.cli.main
from numba.core.typing import cffi_utils
print(cffi_utils.SUPPORTED, "pycparser" in sys.modules)
"""


def test_the_command_line_keeps_numba_from_building_cffi_s_parser():
    """numba's typing builds cffi's C parser when cffi is installed (0.06-0.24 s of every start): the
    command line keeps cffi out (spctool.cli's docstring) unless SPCTOOL_CFFI=1."""
    import os

    def probe(**extra):
        env = {k: v for k, v in os.environ.items() if k != "SPCTOOL_CFFI"} | extra
        run = subprocess.run([sys.executable, "-c", _CFFI_PROBE], capture_output=True, text=True, env=env)
        return run.stdout.split()

    assert probe() == ["False", "False"]
    installed = subprocess.run([sys.executable, "-c", "import cffi"], capture_output=True).returncode == 0
    assert probe(SPCTOOL_CFFI="1") == [str(installed), str(installed)]


_NUMBA_BLAS_PROBE = """
import sys
import numpy as np
import spctool.cli.main
from spctool.geometry import _heightkernels as hk
h = np.arange(25.0).reshape(5, 5)
hx, hy, ok = np.empty_like(h), np.empty_like(h), np.empty(h.shape, np.bool_)
hk.slopes(h, np.ones(h.shape, np.bool_), hx, hy, ok)  # numba's first kernel in this process
import numba.np.arraymath as am, numba.np.linalg as la
print("scipy.linalg" in sys.modules, am._HAVE_BLAS, am.ensure_blas is la.ensure_blas, float(hx[2, 2]))
"""


def test_the_command_line_spares_numba_s_first_kernel_the_scipy_linalg_import():
    """numba's BLAS probe imports scipy.linalg at the first kernel of a process (0.3-0.4 s): the command
    line answers it "no BLAS" (spctool's kernels use no np.correlate/np.convolve, the only users), and
    puts numba's own probe back; SPCTOOL_BLAS_PROBE=1 runs it."""
    import os

    def probe(**extra):
        env = {k: v for k, v in os.environ.items() if k != "SPCTOOL_BLAS_PROBE"} | extra
        cmd = [sys.executable, "-c", _NUMBA_BLAS_PROBE]
        run = subprocess.run(cmd, capture_output=True, text=True, env=env)
        assert run.returncode == 0, run.stderr
        return run.stdout.split()

    assert probe() == ["False", "False", "True", "5.0"]
    assert probe(SPCTOOL_BLAS_PROBE="1") == ["True", "True", "True", "5.0"]


_NUMBA_LIGHT_LOAD = """
import sys
import numpy as np
loaded_before = "importlib.metadata" in sys.modules  # by the interpreter's start (a .pth file)
import spctool.cli.main
from spctool.geometry import _heightkernels as hk
print("scipy" in sys.modules, "yaml" in sys.modules)  # numba imported, without them
h = np.arange(25.0).reshape(5, 5) ** 2
hx, hy, ok = np.empty_like(h), np.empty_like(h), np.empty(h.shape, np.bool_)
hk.slopes(h, np.ones(h.shape, np.bool_), hx, hy, ok)  # numba's first kernel in this process
print(sum(hk.slopes.stats.cache_hits.values()), "numba.np.arraymath" in sys.modules, float(hx[2, 2]))
import numba
lazy = type(sys.modules["importlib.metadata"]).__name__ == "_LazyModule"
print("metadata", "loaded" if loaded_before else lazy, numba.core.entrypoints._already_initialized)

@numba.njit
def twice(h, ok):  # compiled now, after the light load: numba's compiler refreshes its registries
    hx, hy, out = np.empty_like(h), np.empty_like(h), np.empty(h.shape, np.bool_)
    hk.slopes(h, ok, hx, hy, out)
    return 2.0 * hx[2, 2]

print(twice(h, np.ones(h.shape, np.bool_)), "numba.np.arraymath" in sys.modules)
import scipy, yaml  # both import as usual afterwards
print(bool(scipy.__version__), bool(yaml.__version__))
"""


def test_the_command_line_loads_a_cached_kernel_without_numba_s_registry_refresh(tmp_path):
    """A cached kernel needs numba's runtime, not the typing and lowering registries of all of numba
    (~0.22 s of CPU in every process that runs a kernel): the command line loads it without them,
    numba's compiler still refreshes them when a kernel compiles, and numba's import finds neither
    SciPy nor PyYAML (both import as usual afterwards) and does not scan every distribution for
    numba extensions (importlib.metadata left unexecuted); SPCTOOL_NUMBA_REFRESH=1 and
    SPCTOOL_NUMBA_EXTENSIONS=1 keep numba's ways."""
    import os

    def probe(**extra):
        env = {k: v for k, v in os.environ.items() if k != "SPCTOOL_NUMBA_REFRESH"} | extra
        env["NUMBA_CACHE_DIR"] = str(tmp_path)  # compiled by the first run, loaded by the next
        run = subprocess.run(
            [sys.executable, "-c", _NUMBA_LIGHT_LOAD], capture_output=True, text=True, env=env, cwd=tmp_path
        )
        assert run.returncode == 0, run.stderr
        return run.stdout.split()

    h = np.arange(25.0).reshape(5, 5) ** 2
    slope = float(np.gradient(h, axis=0)[2, 2])  # HGT2SLP's central difference along axis 0: 120
    first = probe()  # compiles slopes into the empty cache: numba's compiler loads the registries
    lazy = first[6] if first[6] == "loaded" else "True"  # "loaded": imported by the interpreter's start
    after = [str(slope), "metadata", lazy, "True", str(2 * slope), "True", "True", "True"]
    assert first == ["False", "False", "0", "True"] + after
    light = probe()  # loads it: no registries, until `twice` compiles
    assert light == ["False", "False", "1", "False"] + after
    assert probe(SPCTOOL_NUMBA_REFRESH="1")[2:4] == ["1", "True"]  # numba's refresh at the load
    scanned = probe(SPCTOOL_NUMBA_EXTENSIONS="1")[5:8]  # numba's scan at the first kernel
    assert scanned == ["metadata", "loaded" if lazy == "loaded" else "False", "True"]


_NUMBA_ENV_KERNEL = """
import numba
import numpy as np

@numba.njit(cache=True)
def fill(n):
    a = np.empty(n)  # numba's np.empty: an environment of numba.np.arrayobj in the cached kernel
    for i in range(n):
        a[i] = i * 0.5
    return a
"""

_NUMBA_ENV_PROBE = """
import sys
import spctool.cli.main
sys.path.insert(0, ".")
import kernel
a = kernel.fill(5)
print(sum(kernel.fill.stats.cache_hits.values()), "numba.np.arrayobj" in sys.modules, a.tolist())
if len(sys.argv) > 1:  # a kernel compiled after the load, calling the loaded one
    print(__import__("numba").njit(lambda n: kernel.fill(n)[n - 1])(4), "numba.np.arrayobj" in sys.modules)
"""


def test_the_command_line_loads_a_cached_kernel_without_importing_numba_s_array_module(tmp_path):
    """Unpickling a cached kernel's environments imported the numba modules they name
    (numba.np.arrayobj for np.empty: 0.04-0.07 s at every command's first kernel); the command line
    gives an environment of a numba module not yet imported its name only (nopython code reads only
    its constants). The kernel's result is the same, a kernel compiled afterwards imports the module
    as usual, and SPCTOOL_NUMBA_REFRESH=1 keeps numba's rebuild."""
    import os

    (tmp_path / "kernel.py").write_text(_NUMBA_ENV_KERNEL)

    def probe(*args, **extra):
        env = {k: v for k, v in os.environ.items() if k != "SPCTOOL_NUMBA_REFRESH"} | extra
        env["NUMBA_CACHE_DIR"] = str(tmp_path / "cache")
        cmd = [sys.executable, "-c", _NUMBA_ENV_PROBE, *args]
        run = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=tmp_path)
        assert run.returncode == 0, run.stderr
        return run.stdout.split("\n")[:2]

    values = "[0.0, 0.5, 1.0, 1.5, 2.0]"
    assert probe()[0] == f"0 True {values}"  # compiled: numba imports it to compile
    assert probe() == [f"1 False {values}", ""]  # loaded: not imported
    assert probe("compile") == [f"1 False {values}", "1.5 True"]  # imported when a kernel compiles
    assert probe(SPCTOOL_NUMBA_REFRESH="1")[0] == f"1 True {values}"


def test_numba_s_thread_count_is_read_without_starting_its_pool():
    """register and the renderer ask numba's thread count in every command; numba's get_num_threads
    starts its threading layer to answer (~0.01 s): spctool.threads answers from numba's configuration
    until the pool runs, and numba's answer after (set_num_threads included)."""
    code = (
        "import numba\nfrom numba.np.ufunc import parallel\nfrom spctool.threads import numba_threads\n"
        "n = numba_threads()\nprint(parallel._is_initialized, n == numba.config.NUMBA_NUM_THREADS)\n"
        "print(n == numba.get_num_threads(), parallel._is_initialized)\n"
        "numba.set_num_threads(1)\nprint(numba_threads())\n"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    assert run.stdout.split() == ["False", "True", "True", "True", "1"]


_FAST_EXIT_PROBE = """
import atexit, sys

class Sentinel:
    def __del__(self):  # runs in the interpreter's teardown only
        sys.stderr.write("teardown\\n")

sentinel = Sentinel()
atexit.register(lambda: sys.stderr.write("atexit\\n"))
from spctool.cli.main import cli
cli()
"""


def test_the_command_line_ends_its_process_without_the_interpreter_s_teardown(tmp_path):
    """After a command, the process ends without the interpreter's teardown (0.15-0.3 s of freeing
    numba's code and every module, spctool.cli.main._end_process): exit handlers still run, both
    streams are complete, exit codes are kept; SPCTOOL_FULL_EXIT=1 (and any in-process caller) keeps
    the usual exit."""
    import os

    def run(*args, **extra):
        env = {k: v for k, v in os.environ.items() if k != "SPCTOOL_FULL_EXIT"} | extra
        cmd = [sys.executable, "-c", _FAST_EXIT_PROBE, *args]
        return subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=tmp_path)

    for args in (("--help",), ("man", "register"), ("-C", "nowhere", "info")):
        fast, full = run(*args), run(*args, SPCTOOL_FULL_EXIT="1")
        assert fast.returncode == full.returncode == (2 if "nowhere" in args else 0)
        assert fast.stdout == full.stdout and len(fast.stdout if "nowhere" not in args else "x") > 0
        assert fast.stderr == full.stderr.replace("teardown\n", "")
        assert fast.stderr.endswith("atexit\n") and full.stderr.endswith("atexit\nteardown\n")
