"""The `image2sim` command line. It builds each stage's options and calls the library; no logic lives only here.

Bad input of any kind ends with one line on stderr, naming the problem and the fix, and exit code 2.
"""

from __future__ import annotations

import errno
import logging
import os
import signal
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path
from typing import Annotated, Any, NoReturn

import typer

os.environ.setdefault("MUJOCO_GL", "osmesa")

app = typer.Typer(
    name="image2sim",
    help="Turn a video of a real tabletop into a calibrated MuJoCo simulation.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
)

EXIT_BAD_INPUT = 2

# Options that `reconstruct` and `ground` share (the scan side of both commands).
ArucoSizeOption = Annotated[
    float | None,
    typer.Option(help="Side of the ArUco marker's black square in metres (DICT_4X4_50, id 0, on the table)."),
]
KnownExtentOption = Annotated[
    float | None,
    typer.Option(
        help="Longest extent (length, width or height) in metres of the longest object on the table (no marker)."
    ),
]
MaxFramesOption = Annotated[int, typer.Option(help="Use at most this many frames.")]
SfmSeedOption = Annotated[int, typer.Option(help="Random seed (RANSAC, mapper).")]
VerboseOption = Annotated[bool, typer.Option("--verbose", "-v", help="Log each step.")]


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
    outdir = sys.modules.get("reconstruction._outdir")  # loaded by every command that claims an output
    if outdir is not None:
        outdir.release_output_claims()  # a command that checked its output and stopped before writing it


# The stage the running command last reported (`stage_progress`): an internal failure's line names it.
_current_stage: list[str] = []


def _user_errors() -> tuple[type[BaseException], ...]:
    from grounder.errors import GrounderError
    from reconstruction.errors import ReconstructionError
    from scene_export.errors import SceneExportError

    return (GrounderError, ReconstructionError, SceneExportError)


def fail(message: str) -> None:
    """Prints one line (a message over several lines is joined into one) and exits with code 2 (bad input)."""
    for link, given in _ARGUMENT_LINKS.items():  # the user's own path, not the stand-in (`_reachable_arguments`)
        message = message.replace(link, given)
    typer.echo(f"image2sim: error: {' '.join(message.split())}", err=True)
    raise typer.Exit(EXIT_BAD_INPUT)


def require(*rules: tuple[str, object, bool, str]) -> None:
    """Fails (one line, exit 2) naming each option whose value breaks its rule; rules are (flag, value, ok, rule)."""
    broken = [f"{flag} {value} must be {rule}" for flag, value, ok, rule in rules if not ok]
    if broken:
        fail("; ".join(broken))


@contextmanager
def user_errors_exit_2() -> Iterator[None]:
    try:
        yield
    except _user_errors() as exc:
        fail(str(exc))


@contextmanager
def stage_progress() -> Iterator[Callable[[str, int, int], None]]:
    """A rich progress line per stage, on stderr so stdout stays machine-readable."""
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    console = Console(stderr=True)
    progress = Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=console,
        transient=False,
        disable=not console.is_terminal and "CI" in os.environ,
    )
    tasks: dict[str, Any] = {}

    def report(stage: str, done: int, total: int) -> None:
        _current_stage[:] = [stage]
        if not tasks:  # shown from the first stage on: input rejected before any work is one error line alone
            progress.start()
        if stage not in tasks:
            for other in tasks.values():
                task = progress.tasks[other]
                progress.update(other, completed=task.total)
            tasks[stage] = progress.add_task(stage, total=max(total, 1))
        progress.update(tasks[stage], completed=done, total=max(total, 1))

    try:
        yield report
        for task_id in tasks.values():  # done: the last stage shows complete too
            progress.update(task_id, completed=progress.tasks[task_id].total)
    except BaseException:
        if all(task.completed == 0 for task in progress.tasks):  # refused before any work: the error line alone
            for task_id in tasks.values():
                progress.remove_task(task_id)
        raise
    finally:
        if tasks:
            progress.stop()


def _setup_logging(verbose: bool) -> None:
    from rich.console import Console
    from rich.logging import RichHandler

    logging.basicConfig(  # on stderr with the progress: stdout keeps only the results' lines
        level=logging.INFO if verbose else logging.WARNING,
        format="%(message)s",
        handlers=[RichHandler(console=Console(stderr=True), show_time=False, show_path=False, markup=False)],
    )


@app.command()
def reconstruct(
    source: Annotated[Path, typer.Argument(help="A video file or a folder of images.")],
    out: Annotated[Path, typer.Option("-o", "--out", help="Output folder (created; must be new or empty).")],
    aruco_size: ArucoSizeOption = None,
    known_extent: KnownExtentOption = None,
    max_frames: MaxFramesOption = 150,
    overwrite: Annotated[
        bool, typer.Option(help="Replace a non-empty output folder once the result is ready.")
    ] = False,
    seed: SfmSeedOption = 0,
    verbose: VerboseOption = False,
) -> None:
    """Cameras in a metric, gravity-aligned world frame: COLMAP model, transforms.json, reconstruct.json."""
    _setup_logging(verbose)
    with user_errors_exit_2():
        from reconstruction import ReconstructOptions
        from reconstruction import reconstruct as run_reconstruct

        defaults = ReconstructOptions()
        options = ReconstructOptions(
            aruco_size_m=aruco_size,
            known_extent_m=known_extent,
            frames=replace(defaults.frames, max_frames=max_frames),
            sfm=replace(defaults.sfm, seed=seed),
        )
        with stage_progress() as progress:
            result = run_reconstruct(source, out, options, overwrite=overwrite, progress=progress)
    scale = result.world.scale_source
    typer.echo(
        f"registered {len(result.frames)}/{len(result.selected_frame_indices)} frames "
        f"(reprojection {result.mean_reprojection_error_px:.2f} px, scale from {scale}); wrote {out}"
    )


@app.command()
def ground(
    source: Annotated[Path, typer.Argument(help="A video file or a folder of images of the tabletop.")],
    out: Annotated[Path, typer.Option("-o", "--out", help="Output scene folder (created; must be new or empty).")],
    aruco_size: ArucoSizeOption = None,
    known_extent: KnownExtentOption = None,
    max_frames: MaxFramesOption = 150,
    face_budget: Annotated[int, typer.Option(help="Faces per object mesh after decimation.")] = 4000,
    max_hulls: Annotated[int, typer.Option(help="Convex hulls per object (CoACD).")] = 16,
    density: Annotated[
        float, typer.Option(help="Density (kg/m^3) given to every object when the property model is off.")
    ] = 600.0,
    property_model: Annotated[
        bool,
        typer.Option(help="Predict density, friction and contact per object with the learned property model."),
    ] = True,
    overwrite: Annotated[bool, typer.Option(help="Replace a non-empty output folder once the scene is ready.")] = False,
    seed: SfmSeedOption = 0,
    interaction: Annotated[
        Path | None,
        typer.Option(
            help="A clip of the same objects moving (pushed, dropped, tossed): track it and calibrate the scene to it."
        ),
    ] = None,
    object_markers: Annotated[
        Path | None,
        typer.Option(help="With --interaction: JSON layout of ArUco markers stuck on the objects (see `track`)."),
    ] = None,
    calibration: Annotated[
        str,
        typer.Option(
            help="With --interaction: 'impacts' (each contact after a tracked free flight, rolled out from the fit "
            "of the whole flight; what no landing resolves, e.g. an object that only slides, is calibrated on "
            "windows), 'windows' (short windows rolled out from tracked states) or 'shooting' (multiple shooting "
            "over each object's whole tracked run: slower, does not rest on the tracked states)."
        ),
    ] = "impacts",
    verbose: VerboseOption = False,
) -> None:
    """Film a tabletop, get a MuJoCo scene: scene.xml, assets/, scene.json, preview.png.

    With --interaction CLIP: also track the objects in the clip and calibrate their friction and contact to it.
    """
    _setup_logging(verbose)
    require(
        # kg/m^3: from foams to osmium (22590), the densest element; 1e300 gave a scene of 4e298 kg objects
        ("--density", density, 1.0 <= density <= 25_000.0, "between 1 and 25000 (kg/m^3)"),
        ("--face-budget", face_budget, 100 <= face_budget <= 200_000, "between 100 and 200000"),
        ("--max-hulls", max_hulls, max_hulls >= 1, ">= 1"),
    )
    with user_errors_exit_2():
        from grounder._ground import GroundOptions
        from grounder._ground import ground as run_ground
        from reconstruction import ReconstructOptions

        defaults = GroundOptions()
        recon = ReconstructOptions(
            aruco_size_m=aruco_size,
            known_extent_m=known_extent,
            frames=replace(defaults.reconstruct.frames, max_frames=max_frames),
            sfm=replace(defaults.reconstruct.sfm, seed=seed),
        )
        options = replace(
            defaults,
            reconstruct=recon,
            objects=replace(defaults.objects, mesh=replace(defaults.objects.mesh, face_budget=face_budget)),
            collision=replace(defaults.collision, max_hulls=max_hulls),
            default_density_kg_m3=density,
            property_model=property_model,
        )
        if object_markers is not None and interaction is None:
            fail("--object-markers needs --interaction CLIP: the markers are tracked in the interaction clip")
        if calibration != "impacts" and interaction is None:
            fail("--calibration needs --interaction CLIP: it is how the scene is calibrated to the clip")
        if interaction is not None:
            from grounder._interaction import CALIBRATION_METHODS, InteractionOptions, ground_with_interaction
            from grounder._track import TrackOptions
            from grounder._track_markers import load_object_markers

            if not interaction.exists():
                fail(f"interaction clip {interaction} does not exist; give the path of a video of the objects moving")
            if calibration not in CALIBRATION_METHODS:
                fail(f"--calibration {calibration!r} is not a method; use one of {', '.join(CALIBRATION_METHODS)}")
            markers = () if object_markers is None else load_object_markers(object_markers)
            interaction_options = InteractionOptions(
                ground=options, track=TrackOptions(object_markers=markers), calibration=calibration
            )
            with stage_progress() as progress:
                calibrated = ground_with_interaction(
                    source, interaction, out, interaction_options, overwrite=overwrite, progress=progress
                )
            typer.echo(f"calibrated scene: {calibrated.scene_xml}")
            return
        with stage_progress() as progress:
            result = run_ground(source, out, options, overwrite=overwrite, progress=progress)
    worst = max((d for d, _ in result.settle.values()), default=0.0)
    typer.echo(
        f"{len(result.object_names)} object(s), scale from {result.scale_source}, "
        f"max drift after {defaults.settle_seconds:.0f} s: {worst * 1000:.1f} mm"
    )
    typer.echo(f"MJCF: {result.scene_xml}")


# Later capabilities add their subcommands from their own modules (each defines `register(app)`), so the command
# groups stay next to the code they drive.
_SUBCOMMAND_MODULES = ("cli_properties", "cli_calibrate", "cli_residual", "cli_diagnose", "cli_track")


def _register_subcommands() -> None:
    import importlib
    import importlib.util

    for name in _SUBCOMMAND_MODULES:
        if importlib.util.find_spec(f"grounder.{name}") is not None:
            importlib.import_module(f"grounder.{name}").register(app)


_register_subcommands()


class _Terminated(BaseException):
    """SIGTERM (`timeout`, `docker stop`, a cancelled CI job) as an exception, so that every output stage cleans up
    the way it does for Ctrl-C; a BaseException, so no `except Exception` on the way swallows it."""


def _terminated(signum: int, frame: object) -> None:
    raise _Terminated


# Stand-in paths for arguments whose bytes are not UTF-8, and the arguments as given (`_reachable_arguments`).
_ARGUMENT_LINKS: dict[str, str] = {}
_OUTPUT_OPTIONS = ("-o", "--out")


def _reachable_arguments(argv: list[str], link_dir: Path) -> list[str]:
    """`argv` with each existing input path whose bytes are not UTF-8 (a name in another encoding: a file system
    takes any bytes but '/') replaced by a UTF-8 stand-in: a symbolic link in `link_dir` to the deepest folder of the
    path whose name is not UTF-8 (or to the file itself, when only its name is), followed by the rest of the path.
    OpenCV, COLMAP and MuJoCo take paths as UTF-8 strings, and crashed (SIGSEGV) or refused (a TypeError) on others; a
    folder link keeps the files beside a scene (its meshes) where the scene's relative paths look for them. Output
    folders (`-o`) keep their names: they are staged under UTF-8 names and renamed at the end."""
    from reconstruction._outdir import is_utf8_path

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
        _ARGUMENT_LINKS[stand_in] = arg
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
            _ARGUMENT_LINKS.clear()
    sys.exit(code if isinstance(code, int) else 0)


_STOPPED_BY_CTRL_C = "image2sim: stopped (Ctrl-C); nothing half-written was left"


def _full_disk(argv: list[str], filename: str | None) -> NoReturn:
    """One line saying which disk filled and what to free, exit 2. A write inside a library (numpy's zip, faiss) may
    not name its file: the output folder (`-o X`, `--out X`) is where it was."""
    from reconstruction._outdir import no_space_advice

    given_out = next((argv[i + 1] for i, a in enumerate(argv[:-1]) if a in _OUTPUT_OPTIONS), None)
    typer.echo(f"image2sim: error: {no_space_advice(filename or given_out or '.')}", err=True)
    sys.exit(2)


def _run(argv: list[str], *, debug: bool = False) -> object:
    """`main`'s work: the command's exit code, or one line and `sys.exit` for what stopped it."""
    # typer 0.29 carries its own click (`constraints.txt` pins it); its exceptions are not re-exported by `typer`.
    from typer._click.exceptions import ClickException, NoArgsIsHelpError, UsageError

    _current_stage.clear()  # an earlier command's stage in this process (the tests run many) is not this one's
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
        stage = f" ({_current_stage[0]})" if _current_stage else ""
        detail = " ".join(str(exc).split())[:300].rstrip(".") or "no message"
        hint = "the traceback is above" if debug else "run the same command with --debug for the traceback"
        typer.echo(
            f"image2sim: internal error in {command}{stage}: {type(exc).__name__}: {detail}; {hint}, and please "
            "report it",
            err=True,
        )
        sys.exit(1)
    return code


if __name__ == "__main__":
    main()
