"""The `image2sim` command line. It builds each stage's options and calls the library; no logic lives only here.

Bad input of any kind ends with one line on stderr, naming the problem and the fix, and exit code 2. Each command
group lives in its own module (``scan``, ``properties``, ``calibrate``, ``residual``, ``diagnose``, ``track``) and
adds itself to `app` with ``register(app)``; shared helpers are in ``grounder.cli.common``.
"""

from __future__ import annotations

import errno
import os
import signal
import sys
from pathlib import Path
from typing import Annotated, NoReturn

import typer

from grounder.cli import calibrate, diagnose, properties, residual, scan, track
from grounder.cli.common import ARGUMENT_LINKS, current_stage
from image2sim_common.headless_gl import choose_headless_gl

choose_headless_gl(even_with_display=True)  # the command line renders off-screen only

app = typer.Typer(
    name="image2sim",
    help="Turn a video of a real tabletop into a calibrated MuJoCo simulation.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
)


@app.callback()
def _group(
    ctx: typer.Context,
    debug: Annotated[
        bool, typer.Option("--debug", help="On an internal failure, print the traceback too (any position).")
    ] = False,
) -> None:
    """Turn a video of a real tabletop into a calibrated MuJoCo simulation."""
    ctx.call_on_close(_release_output_claims)  # however the command ends: its output folders are free again


def _release_output_claims() -> None:
    outdir = sys.modules.get("image2sim_common.outdir")  # loaded by every command that claims an output
    if outdir is not None:
        outdir.release_output_claims()  # a command that checked its output and stopped before writing it


for _commands in (scan, properties, calibrate, residual, diagnose, track):
    _commands.register(app)


class _Terminated(BaseException):
    """SIGTERM (`timeout`, `docker stop`, a cancelled CI job) as an exception, so that every output stage cleans up
    the way it does for Ctrl-C; a BaseException, so no `except Exception` on the way swallows it."""


def _terminated(signum: int, frame: object) -> None:
    raise _Terminated


_OUTPUT_OPTIONS = ("-o", "--out")


def _reachable_arguments(argv: list[str], link_dir: Path) -> list[str]:
    """`argv` with each existing input path whose bytes are not UTF-8 (a name in another encoding: a file system
    takes any bytes but '/') replaced by a UTF-8 stand-in: a symbolic link in `link_dir` to the deepest folder of the
    path whose name is not UTF-8 (or to the file itself, when only its name is), followed by the rest of the path.
    OpenCV, COLMAP and MuJoCo take paths as UTF-8 strings, and crashed (SIGSEGV) or refused (a TypeError) on others; a
    folder link keeps the files beside a scene (its meshes) where the scene's relative paths look for them. Output
    folders (`-o`) keep their names: they are staged under UTF-8 names and renamed at the end."""
    from image2sim_common.outdir import is_utf8_path

    out = []
    for i, arg in enumerate(argv):
        is_output = (i > 0 and argv[i - 1] in _OUTPUT_OPTIONS) or arg.startswith(
            tuple(f"{o}=" for o in _OUTPUT_OPTIONS)
        )
        if is_utf8_path(arg) or is_output or not os.path.lexists(arg):
            out.append(arg)
            continue
        parts = Path(os.path.abspath(arg)).parts
        last_odd = max(k for k, part in enumerate(parts) if not is_utf8_path(part))
        rest: tuple[str, ...] = ()
        if last_odd == len(parts) - 1 and not Path(arg).is_dir():
            target = Path(*parts)
            name = f"arg{i}{''.join(s for s in Path(arg).suffixes if is_utf8_path(s))}"
        else:
            target, rest, name = Path(*parts[: last_odd + 1]), parts[last_odd + 1 :], f"arg{i}"
        link = link_dir / name
        os.symlink(target, link)
        stand_in = str(Path(link, *rest))
        ARGUMENT_LINKS[stand_in] = arg
        out.append(stand_in)
    return out


def main(argv: list[str] | None = None) -> None:
    """Console-script entry point.

    Usage errors (unknown option or command, a value of the wrong type, a missing argument) get the same one line
    as every other bad input, `image2sim: error: ...`, and exit code 2, instead of click's boxed usage message.
    """
    import shutil
    import tempfile

    signal.signal(signal.SIGTERM, _terminated)
    argv = list(sys.argv[1:] if argv is None else argv)
    debug = "--debug" in argv  # taken anywhere on the line, before or after the command
    argv = [a for a in argv if a != "--debug"]
    link_dir = None
    try:
        # Bytes that are not UTF-8 reach Python as lone surrogates (surrogateescape): only then is the (heavy)
        # `reconstruction` package loaded for its path helpers.
        if any("\udc80" <= c <= "\udcff" for arg in argv for c in arg):
            link_dir = Path(tempfile.mkdtemp(prefix="image2sim-args-"))
            argv = _reachable_arguments(argv, link_dir)
        code = _run(argv, debug=debug)
    finally:
        _release_output_claims()
        if link_dir is not None:
            shutil.rmtree(link_dir, ignore_errors=True)
            ARGUMENT_LINKS.clear()
    sys.exit(code if isinstance(code, int) else 0)


_STOPPED_BY_CTRL_C = "image2sim: stopped (Ctrl-C); nothing half-written was left"


def _full_disk(argv: list[str], filename: str | None) -> NoReturn:
    """One line saying which disk filled and what to free, exit 2. A write inside a library (numpy's zip, faiss) may
    not name its file: the output folder (`-o X`, `--out X`) is where it was."""
    from image2sim_common.outdir import no_space_advice

    given_out = next((argv[i + 1] for i, a in enumerate(argv[:-1]) if a in _OUTPUT_OPTIONS), None)
    typer.echo(f"image2sim: error: {no_space_advice(filename or given_out or '.')}", err=True)
    sys.exit(2)


def _run(argv: list[str], *, debug: bool = False) -> object:
    """`main`'s work: the command's exit code, or one line and `sys.exit` for what stopped it."""
    # typer 0.29 carries its own click (`constraints.txt` pins it); its exceptions are not re-exported by `typer`.
    from typer._click.exceptions import ClickException, NoArgsIsHelpError, UsageError

    current_stage.clear()  # an earlier command's stage in this process (the tests run many) is not this one's
    try:
        code = app(args=argv, prog_name="image2sim", standalone_mode=False)
        if code == 128 + signal.SIGINT:  # typer catches a Ctrl-C itself and returns this (no command returns it)
            typer.echo(_STOPPED_BY_CTRL_C, err=True)
    except _Terminated:  # the output stages have removed what they had begun, as for Ctrl-C
        typer.echo("image2sim: stopped (SIGTERM); nothing half-written was left", err=True)
        sys.exit(128 + signal.SIGTERM)
    except NoArgsIsHelpError as exc:  # `image2sim` or a group alone: typer has printed its help already
        sys.exit(exc.exit_code)
    except UsageError as exc:
        command = exc.ctx.command_path if exc.ctx is not None else "image2sim"
        message = " ".join(exc.format_message().split()).rstrip(".")
        typer.echo(f"image2sim: error: {message}; see `{command} --help`", err=True)
        sys.exit(2)
    except ClickException as exc:
        typer.echo(f"image2sim: error: {' '.join(exc.format_message().split())}", err=True)
        sys.exit(exc.exit_code)
    except (typer.Abort, KeyboardInterrupt):  # Ctrl-C: the output stages have cleaned up as for SIGTERM
        typer.echo(_STOPPED_BY_CTRL_C, err=True)
        sys.exit(128 + signal.SIGINT)
    except OSError as exc:  # the system refused a read or write no command check foresaw (permissions, disk full)
        where = f" {exc.filename}" if exc.filename else ""
        if exc.errno == errno.ENOSPC:
            _full_disk(argv, exc.filename)
        typer.echo(
            f"image2sim: error: the system refused to read or write{where} ({exc.strerror or exc}); "
            "check the permissions and free space there, then run again",
            err=True,
        )
        sys.exit(2)
    except Exception as exc:  # a failure no check foresaw: a bug, not bad input
        if "No space left on device" in str(exc):  # a native library's write (faiss, COLMAP) as a RuntimeError
            _full_disk(argv, None)
        if debug:
            import traceback

            traceback.print_exc()
        command = next((a for a in argv if not a.startswith("-")), "image2sim")
        stage = f" ({current_stage[0]})" if current_stage else ""
        detail = " ".join(str(exc).split())[:300].rstrip(".") or "no message"
        hint = "the traceback is above" if debug else "run the same command with --debug for the traceback"
        typer.echo(
            f"image2sim: internal error in {command}{stage}: {type(exc).__name__}: {detail}; {hint}, and please "
            "report it",
            err=True,
        )
        sys.exit(1)
    return code
