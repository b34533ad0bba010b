"""Every ``--help`` example and every README example runs, as written, in a shell (issues 16, 42).

The examples are parsed out of each command's help text (the lines after ``Example:`` /
``Examples:``) and out of README.md's code blocks; they are written with the names of the demo that
ships with spctool (``spctool demo --copy-to demo``: pictures ``P000000001A1`` …, landmarks
``B01980`` …).  Every help example runs twice, one shell line each:

* **in printed order on one copy** (``spctool --help`` first, then each command in the order
  ``spctool --help`` lists them), starting from a directory with no demo: the first example copies
  it and makes ``demo/sel.txt`` and ``demo/reg.txt``, so a later example that breaks the demo for the
  ones after it (as make-maplets appending 74 maplets to its LMRKLIST did) fails them;
* **each on a fresh copy**, so that no example silently needs an earlier one: a directory holding
  ``demo/`` (a copy of the demo working directory, with ``sel.txt`` and ``reg.txt``, the README
  session's lithos-select and register tables, inside it, since ``-C demo`` makes relative paths
  relative to ``demo/`` like ``git -C``) — or no ``demo/`` for an example that copies it there — and
  ``fixtures``, a link to the checkout's ``fixtures/`` (real mission files), read only.  An example
  that reads what an earlier line of the same help writes (``shape.obj``, ``world.toml``) runs after
  those lines, listed in :data:`NEEDS` (checked to be earlier lines of the same help).

``spctool`` on the PATH is this checkout's command line.  A non-zero exit status fails the test with
the example and its stderr; ``| jq`` filters must not print ``null``.  The only examples not
executed are listed in :data:`NOT_RUN` with the reason.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"

#: examples not executed, with the reason (the only exceptions)
NOT_RUN = {
    "spctool -C demo batch --scheduler tcp://127.0.0.1:8786 --out-dir run1": "needs a running Dask "
    "scheduler (a cluster on the network)",
    "spctool -C demo batch --scheduler tcp://HOST:8786 --out-dir run1": "needs a running Dask scheduler "
    "(a cluster on the network)",
    "pip install -e .": "installs the package (the suite runs this checkout's spctool)",
    "pip install -e '.[test]'": "installs the package (the suite runs this checkout's spctool)",
    "pytest": "runs this test suite itself",
}


#: examples that read a file an earlier line of the same help writes: those lines, run first
_GEO_BATCH = "spctool -q -C demo batch --out-dir geo-out"
NEEDS = {
    "spctool convert shape.obj SHAPE.TXT": ["spctool convert demo/SHAPEFILES/SHAPE.TXT shape.obj"],
    "spctool convert --flip-rows P1.fits upside_down.png": [
        "spctool convert --sum demo/SUMFILES/P000000001A1.SUM demo/IMAGEFILES/P000000001A1.DAT P1.fits"
    ],
    "spctool simulate world.toml WORLD": ["spctool simulate --example > world.toml"],
    "spctool -C WORLD lithos-select P000000001A1": [
        "spctool simulate --example > world.toml",
        "spctool simulate world.toml WORLD",
    ],
    **{
        f"spctool -C demo geometry --from-batch geo-out {rest}": [_GEO_BATCH]
        for rest in (
            "--dry-run",
            "--mode alternate --dry-run --json",
            "--report-dir geo-report --plot geometry.png",
        )
    },
}


def _command_help(name: str | None) -> str:
    import click

    from spctool.cli.main import cli

    if name is None:
        return cli.help or ""
    ctx = click.Context(cli, info_name="spctool")
    return cli.get_command(ctx, name).help or ""


def help_examples(help_text: str) -> list[str]:
    """The example lines of a command's help: after 'Example:'/'Examples:', the indented lines of
    the verbatim (``\\b``) block that start with ``spctool`` (or ``cd DIR && spctool …``)."""
    out, on = [], False
    for line in help_text.splitlines():
        st = line.strip()
        if re.match(r"^examples?:$", st, re.IGNORECASE):
            on = True
            continue
        if on:
            if st.startswith(("spctool", "cd ")):
                out.append(st)
            elif st in ("\b", ""):
                continue
            else:
                on = False
    return out


def readme_blocks() -> list[tuple[str, str]]:
    """README code blocks as (language, text): '' (shell) and 'python'; other fences are not code."""
    blocks = re.findall(r"^```(\w*)\n(.*?)^```", README.read_text(encoding="utf-8"), re.MULTILINE | re.DOTALL)
    out = []
    for lang, text in blocks:
        if lang == "python" or (
            lang == ""
            and any(ln.strip().startswith(("spctool ", "pip ", "pytest", "cd ")) for ln in text.splitlines())
        ):
            out.append((lang, text))
    return out


def _commands():
    from spctool.cli.main import COMMANDS

    return list(COMMANDS)


# ------------------------------------------------------------------------------------------------
# the directory the examples run in


_JQ_SHIM = r'''#!{python}
"""jq stand-in for machines without jq: path filters such as .a, .a.b, .a[0].b, '.files[0].scale'."""
import json, re, sys
doc = json.load(sys.stdin)
for key, index in re.findall(r"\.(\w+)|\[(\d+)\]", sys.argv[-1]):
    doc = (doc.get(key) if isinstance(doc, dict) else None) if key else (
        doc[int(index)] if isinstance(doc, list) and int(index) < len(doc) else None)
print(json.dumps(doc, indent=2))
'''


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    """demo/ (with sel.txt, reg.txt), fixtures -> the checkout's, bin/ with spctool (and jq)."""
    from click.testing import CliRunner

    from spctool.cli.main import cli

    root = tmp_path_factory.mktemp("examples")
    run = CliRunner().invoke
    assert run(cli, ["demo", "--copy-to", str(root / "demo")]).exit_code == 0
    demo = root / "demo"
    sel = run(cli, ["-C", str(demo), "-q", "lithos-select", "P000000001A1", "-o", "sel.txt"])
    assert sel.exit_code == 0, sel.stderr
    reg = run(
        cli, ["-C", str(demo), "-q", "register", "P000000001A1", "--landmarks", "sel.txt", "-o", "reg.txt"]
    )
    assert reg.exit_code == 0, reg.stderr
    (root / "fixtures").symlink_to(ROOT / "fixtures")
    bin_dir = root / "bin"
    bin_dir.mkdir()
    tool = bin_dir / "spctool"
    tool.write_text(f'#!/bin/sh\nexec "{sys.executable}" -m spctool.cli.main "$@"\n')
    tool.chmod(0o755)
    if shutil.which("jq") is None:
        jq = bin_dir / "jq"
        jq.write_text(_JQ_SHIM.replace("{python}", sys.executable))
        jq.chmod(0o755)
    return root


def _env(base_dir: Path) -> dict:
    env = dict(os.environ)
    env["PATH"] = f"{base_dir / 'bin'}{os.pathsep}{env.get('PATH', '')}"
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT)] + [p for p in [env.get("PYTHONPATH")] if p])
    env.pop("COLUMNS", None)
    return env


def _fresh(base_dir: Path, tmp_path: Path, with_demo: bool = True) -> Path:
    """A private copy of the example directory (the demo copied, fixtures linked)."""
    work = tmp_path / "w"
    work.mkdir()
    if with_demo:
        shutil.copytree(base_dir / "demo", work / "demo")
    (work / "fixtures").symlink_to(ROOT / "fixtures")
    return work


def _run(script: str, cwd: Path, env: dict, what: str) -> subprocess.CompletedProcess:
    res = subprocess.run(
        ["bash", "-e", "-o", "pipefail", "-c", script],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert res.returncode == 0, (
        f"{what} failed (exit {res.returncode}):\n{script}\n--- stderr:\n{res.stderr[-3000:]}"
    )
    if "| jq" in script:
        assert "null" not in res.stdout.split(), f"{what}: jq printed null:\n{script}\n{res.stdout[-2000:]}"
    return res


# ------------------------------------------------------------------------------------------------
# the tests


def test_every_command_has_examples():
    for name in _commands():
        assert help_examples(_command_help(name)), f"spctool {name} --help has no example"


def test_not_run_examples_still_exist():
    """Every exception in NOT_RUN is an example somewhere (no stale exceptions)."""
    lines = {ex for name in [None, *_commands()] for ex in help_examples(_command_help(name))}
    for _, text in readme_blocks():
        lines |= {ln.split("#")[0].strip() for ln in text.splitlines()}
    stale = [ex for ex in NOT_RUN if ex not in lines]
    assert not stale, stale


def _all_examples() -> list[tuple[str, int, str]]:
    """(command or '', index in its help, example) of every help example, in printed order."""
    return [
        (name or "", k, ex)
        for name in [None, *_commands()]
        for k, ex in enumerate(help_examples(_command_help(name)))
    ]


def _slow_example(ex: str) -> bool:
    """Examples of a minute or more: the s16-50m Monte Carlo scene, the example world of simulate."""
    return "--preset s16-50m" in ex or ex in NEEDS and "spctool simulate world.toml WORLD" in [ex, *NEEDS[ex]]


def test_needs_are_earlier_lines_of_the_same_help():
    examples = _all_examples()
    for ex, needed in NEEDS.items():
        where = [(c, k) for c, k, e in examples if e == ex]
        assert where, f"NEEDS names an example that is no more: {ex}"
        for c, k in where:
            earlier = [e for c2, k2, e in examples if c2 == c and k2 < k]
            assert all(n in earlier for n in needed), (ex, needed)


@pytest.mark.slow
def test_every_example_in_printed_order_on_one_copy(base, tmp_path):
    """All help examples, in the order printed, in one directory that starts without the demo."""
    work = _fresh(base, tmp_path, with_demo=False)
    env = _env(base)
    ran = 0
    for command, _, ex in _all_examples():
        if ex in NOT_RUN:
            continue
        _run(ex, work, env, f"'spctool {command} --help' example (in printed order, on one copy)")
        ran += 1
    assert ran >= 50


@pytest.mark.parametrize(
    "command,index,example",
    [
        pytest.param(
            *e, id=f"{e[0] or 'spctool'}-{e[1]}", marks=[pytest.mark.slow] if _slow_example(e[2]) else []
        )
        for e in _all_examples()
        if e[2] not in NOT_RUN
    ],
)
def test_each_example_on_a_fresh_copy(command, index, example, base, tmp_path):
    work = _fresh(base, tmp_path, with_demo="--copy-to demo" not in example)
    env = _env(base)
    for needed in NEEDS.get(example, []):
        _run(needed, work, env, f"'spctool {command} --help' example needed by {example!r}")
    _run(example, work, env, f"'spctool {command} --help' example {index} (alone, on a fresh copy)")


def test_readme_examples_run(base, tmp_path):
    work = _fresh(base, tmp_path, with_demo=False)  # the README makes its own copy of the demo
    env = _env(base)
    blocks = readme_blocks()
    assert len(blocks) >= 4
    for k, (lang, text) in enumerate(blocks):
        if lang == "python":
            script = tmp_path / f"readme_{k}.py"
            script.write_text(text)
            _run(f'"{sys.executable}" {script}', work, env, f"README python block {k}")
            continue
        lines = []
        for ln in text.splitlines():
            cmd = ln.split("#")[0].strip()
            lines.append(f"# not run: {NOT_RUN[cmd]}" if cmd in NOT_RUN else ln)
        _run("\n".join(lines), work, env, f"README block {k}")
