"""What every `image2sim` command shares: one-line errors (exit 2), option checks, progress lines, logging."""

from __future__ import annotations

import logging
import os
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import typer

from image2sim_common.progress import ProgressFn

EXIT_BAD_INPUT = 2

# The stage the running command last reported (`stage_progress`): an internal failure's line names it.
current_stage: list[str] = []

# Stand-in paths for arguments whose bytes are not UTF-8, and the arguments as given (`grounder.cli.entry`).
ARGUMENT_LINKS: dict[str, str] = {}


def user_errors() -> tuple[type[BaseException], ...]:
    from grounder.errors import GrounderError
    from reconstruction.errors import ReconstructionError
    from scene_export.errors import SceneExportError

    return (GrounderError, ReconstructionError, SceneExportError)


def fail(message: str) -> None:
    """Prints one line (a message over several lines is joined into one) and exits with code 2 (bad input)."""
    for link, given in ARGUMENT_LINKS.items():  # the user's own path, not the stand-in (`_reachable_arguments`)
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
    except user_errors() as exc:
        fail(str(exc))


def eta_column() -> Any:
    """A progress column: "ETA m:ss" while a stage of several steps runs (rich's estimate from the steps done so
    far), nothing before its first step, for a one-step stage, or once it is done (its elapsed time says it all)."""
    from rich.progress import ProgressColumn, Task
    from rich.text import Text

    class EtaColumn(ProgressColumn):
        def render(self, task: Task) -> Text:
            remaining = task.time_remaining
            if task.finished or not task.total or task.total <= 1 or not task.completed or remaining is None:
                return Text("")
            seconds = round(remaining)
            return Text(f"ETA {seconds // 60}:{seconds % 60:02d}", style="progress.remaining")

    return EtaColumn()


@contextmanager
def stage_progress() -> Iterator[ProgressFn]:
    """A rich progress line per stage, on stderr so stdout stays machine-readable."""
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    console = Console(stderr=True)
    progress = Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        eta_column(),
        console=console,
        transient=False,
        disable=not console.is_terminal and "CI" in os.environ,
    )
    tasks: dict[str, Any] = {}

    def report(stage: str, done: int, total: int) -> None:
        current_stage[:] = [stage]
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


def setup_logging(verbose: bool) -> None:
    from rich.console import Console
    from rich.logging import RichHandler

    logging.basicConfig(  # on stderr with the progress: stdout keeps only the results' lines
        level=logging.INFO if verbose else logging.WARNING,
        format="%(message)s",
        handlers=[RichHandler(console=Console(stderr=True), show_time=False, show_path=False, markup=False)],
    )
