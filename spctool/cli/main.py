"""The ``spctool`` command group: global options, error handling, subcommand registry.

Errors a user can cause (bad files, bad usage) end as ONE stderr line
``spctool: error: …`` with exit code 2 (1 when a requested check failed, 3 when
the machine refused, 130 on Ctrl-C: :data:`spctool.errors.EXIT_CODES`, listed in
the --help epilog); ``--debug`` shows the traceback instead.  ``-C DIR`` changes
directory like ``git -C`` (restored when :meth:`SpcGroup.main` returns).  Commands register themselves from
their own modules (``spctool/cli/*.py``, :data:`spctool.cli.commands.COMMANDS`), which are imported only
when one of their commands runs: ``spctool info`` does not pay for numba, nor
``spctool --version`` for anything.
"""

from __future__ import annotations

import importlib
import io
import os
import sys
import traceback
import warnings

import click

from spctool import __version__
from spctool.cli.commands import COMMAND_MODULES, COMMANDS  # noqa: F401 (tests take both from here)
from spctool.cli.common import Context
from spctool.errors import EXIT_CODES, SpcEnvironmentError, SpcError, SpcUsageError
from spctool.formats.guard import input_scope


class SpcGroup(click.Group):
    """A click group that reports every error as one line (cli-contract.md exit codes)."""

    def list_commands(self, ctx):
        return list(COMMANDS)  # mission stages first

    def get_command(self, ctx, name):
        """The command ``name``, importing its module on first use (:data:`COMMANDS`)."""
        if name not in self.commands and name in COMMANDS:
            importlib.import_module(COMMANDS[name]).register(self)
        return self.commands.get(name)

    def main(self, args=None, prog_name=None, complete_var=None, standalone_mode=True, **extra):
        if args is None and standalone_mode:  # this process's own command line: it may end the process
            try:
                return self._process_main(prog_name, complete_var, extra)
            except SystemExit as exc:
                _end_process(exc.code)  # returns only when the interpreter must end as usual
                raise
        return self._process_main(prog_name, complete_var, extra, args, standalone_mode)

    def _process_main(self, prog_name, complete_var, extra, args=None, standalone_mode=True):
        args = list(sys.argv[1:] if args is None else args)
        debug = "--debug" in args[: _first_command_index(self, args)]
        cwd = os.getcwd()  # -C changes directory (like git -C); restored for callers in this process
        closed = sys.stdout is None  # started with standard output closed (>&-)
        if closed:
            sys.stdout = _ClosedStdout()
        try:
            with input_scope():  # the files this command reads are never replaced without a .bak
                return self._main(args, prog_name, complete_var, standalone_mode, debug, extra)
        finally:
            if closed:
                sys.stdout = None
            try:
                os.chdir(cwd)
            except OSError:
                pass

    def _main(self, args, prog_name, complete_var, standalone_mode, debug, extra):
        try:
            # numpy's floating-point RuntimeWarnings (file:line, source text) are not for users: an
            # error is reported by its one line alone; with --debug they are shown as usual
            with warnings.catch_warnings():
                if not debug:
                    warnings.simplefilter("ignore", RuntimeWarning)
                rv = super().main(args=args, prog_name=prog_name or "spctool", standalone_mode=False, **extra)
        except click.exceptions.Exit as exc:
            sys.exit(exc.exit_code)
        except click.exceptions.Abort:  # click turns Ctrl-C at a prompt into Abort
            click.echo("spctool: error: interrupted", err=True)
            sys.exit(130)
        except click.ClickException as exc:
            if debug:
                traceback.print_exc()
            hint = ""
            misplaced = isinstance(exc, click.NoSuchOption) and exc.option_name in GLOBAL_OPTIONS
            if misplaced and exc.ctx is not None:
                rest = exc.ctx.command_path.split(" ", 1)[-1]
                hint = (
                    f" ({exc.option_name} is a global option: put it before the command, "
                    f"'spctool {exc.option_name} {rest} ...')"
                )
            elif isinstance(exc, click.UsageError) and exc.ctx is not None:
                hint = f" (see '{exc.ctx.command_path} --help')"
            click.echo(f"spctool: error: {_one_line(exc.format_message())}{hint}", err=True)
            sys.exit(exc.exit_code)
        except SpcError as exc:
            if debug:
                traceback.print_exc()
            click.echo(f"spctool: error: {_one_line(str(exc))}", err=True)
            sys.exit(exc.exit_code)
        except BrokenPipeError:
            sys.exit(0)
        except KeyboardInterrupt:
            click.echo("spctool: error: interrupted", err=True)
            sys.exit(130)
        except OSError as exc:  # the machine refused (permissions, disk full, EIO): exit 3
            if debug:
                traceback.print_exc()
            err = SpcEnvironmentError.from_oserror(exc)
            click.echo(f"spctool: error: {_one_line(str(err))}", err=True)
            sys.exit(err.exit_code)
        except Exception as exc:  # a bug: still one line unless --debug
            if debug:
                traceback.print_exc()
            click.echo(
                f"spctool: error: internal error: {type(exc).__name__}: {_one_line(str(exc))} "
                "(rerun with --debug for a traceback and please report it)",
                err=True,
            )
            sys.exit(1)
        if standalone_mode:
            sys.exit(rv if isinstance(rv, int) else 0)
        return rv


def _end_process(code) -> None:
    """End this process at once with exit status ``code`` once its command is done, without the
    interpreter's teardown: freeing numba's compiled code and LLVM's objects and every module, 0.15-0.3 s
    of CPU and wall after each command had finished its work (issue 42, docs/benchmarks.md).  The exit
    handlers run first (``atexit``: worker pools, temporary folders, logging) and both standard streams
    are flushed, so nothing written is lost.  Returns (the usual exit follows) when a non-daemon thread
    is still running, a stream cannot be flushed (a closed pipe: Python's own report and status), the
    code is not a number, or ``SPCTOOL_FULL_EXIT=1``."""
    import atexit
    import threading

    if os.environ.get("SPCTOOL_FULL_EXIT") == "1":
        return
    status = 0 if code is None else code
    if not isinstance(status, int) or isinstance(status, bool) or not 0 <= status <= 255:
        return
    main = threading.main_thread()
    if any(t is not main and t.is_alive() and not t.daemon for t in threading.enumerate()):
        return
    atexit._run_exitfuncs()
    try:
        for stream in {id(s): s for s in (sys.stdout, sys.stderr, sys.__stdout__, sys.__stderr__)}.values():
            if stream is not None:
                stream.flush()
    except Exception:  # noqa: BLE001 - the interpreter's own exit reports it
        return
    os._exit(status)


class _ClosedStdout(io.TextIOBase):
    """Standard output when the process started without one (``>&-``): writing to it is the
    environment error "standard output is closed" (exit 3, one line), never a silent loss."""

    def writable(self) -> bool:
        return True

    def write(self, text) -> int:
        if not text:
            return 0
        raise SpcEnvironmentError("<stdout>", "standard output is closed (redirect it to a file or use -o)")

    def isatty(self) -> bool:
        return False


#: the group's own options: given after a subcommand, they get a hint instead of a bare "no such option"
GLOBAL_OPTIONS = ("-C", "--settings", "-v", "--verbose", "-q", "--quiet", "--debug", "--spc-columns")


def _first_command_index(group, args):
    for i, a in enumerate(args):
        if a in COMMANDS:
            return i
    return len(args)


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


EPILOG = "Exit codes (every command):\n\n\b\n" + "\n".join(
    f"  {code:>3}  {text}" for code, text in EXIT_CODES.items()
)


@click.group(
    cls=SpcGroup,
    context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100},
    epilog=EPILOG,
)
@click.version_option(__version__, "-V", "--version", prog_name="spctool")
@click.option(
    "-C",
    "workdir",
    default=None,
    metavar="DIR",
    type=click.Path(file_okay=False),
    help="Run as if started in DIR, the SPC working directory (SUMFILES/, MAPFILES/, LMKFILES/, ...), "
    "like git -C: relative paths on the command line are relative to DIR. Default: the current "
    "directory, or the working directory of a PICTURE given as DIR/SUMFILES/NAME.SUM.",
)
@click.option(
    "--settings",
    "settings",
    metavar="FILE",
    type=click.Path(dir_okay=False),
    help="INIT_LITHOS settings file. Default: DIR/INIT_LITHOS.TXT when present.",
)
@click.option("-v", "--verbose", count=True, help="More messages on stderr (repeatable).")
@click.option("-q", "--quiet", is_flag=True, help="Only errors on stderr; no progress bars.")
@click.option("--debug", is_flag=True, help="Show tracebacks on errors.")
@click.option(
    "--spc-columns",
    "spc_columns",
    is_flag=True,
    help="Read section rows (SUM LANDMARKS / LIMB FITS, LMK PICTURES / MAP OVERLAPS / LIMB FITS) exactly "
    "as LITHOS's formatted READs do, in their fixed columns, to reproduce a legacy run. Default: a row "
    "not in SPC's columns is read as its writer meant, with a warning giving both readings.",
)
@click.pass_context
def cli(ctx, workdir, settings, verbose, quiet, debug, spc_columns):
    """spctool — surface-feature optical navigation the SPC way.

    Stages chain through landmark tables (text or --json); with -C DIR, relative paths are
    relative to DIR (like git -C), so the tables below live in the demo's working directory:

    Example:

    \b
      spctool demo --copy-to demo
      spctool -C demo lithos-select P000000001A1 -o sel.txt
      spctool -C demo register P000000001A1 --landmarks sel.txt -o reg.txt
      spctool -C demo solve-pose P000000001A1 --measurements reg.txt --output new.SUM

    Pixels are SPC pixels everywhere: sample (column) and line (row), 1-based, pixel
    centres at integers, line 1 = first stored row.

    Man pages: 'spctool man COMMAND'.  Shell completion (picture and landmark names of the
    working directory too): eval "$(_SPCTOOL_COMPLETE=bash_source spctool)" in ~/.bashrc
    (zsh: zsh_source, fish: fish_source).
    """
    if workdir is not None:
        try:
            os.chdir(workdir)
        except FileNotFoundError:
            raise SpcUsageError(f"-C {workdir}: no such working directory") from None
        except OSError as exc:
            raise SpcUsageError(f"-C {workdir}: {(exc.strerror or 'cannot change to it').lower()}") from None
    ctx.obj = Context(
        workdir=".",
        settings_path=settings,
        verbosity=-1 if quiet else verbose,
        debug=debug,
        explicit_workdir=workdir is not None,
    )
    if spc_columns:
        from spctool.formats.rows import spc_columns_mode

        ctx.with_resource(spc_columns_mode(True))
    if not ctx.resilient_parsing:  # not while completing
        from spctool.cli.jit import first_run_note

        disarm = first_run_note(ctx.obj, ctx.invoked_subcommand)
        if disarm is not None:
            ctx.call_on_close(disarm)


@cli.result_callback()
def _said_after_success(result, **_params):
    """Warnings about how the inputs were read (rows off SPC's columns ...), once the command succeeded."""
    obj = click.get_current_context().obj
    if obj is not None:
        obj.flush_later()
    return result


if __name__ == "__main__":  # pragma: no cover
    cli()
