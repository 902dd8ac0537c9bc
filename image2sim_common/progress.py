"""The progress callback every long stage takes."""

from __future__ import annotations

from collections.abc import Callable

# progress(stage, done, total): the stage's name as a user reads it ("meshing objects"), and how far it is.
ProgressFn = Callable[[str, int, int], None]


def no_progress(stage: str, done: int, total: int) -> None:
    """A progress callback that reports nothing."""
