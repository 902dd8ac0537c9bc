"""Output folders that appear whole or not at all."""

from __future__ import annotations

import contextlib
import os
import secrets
import shutil
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any

import numpy as np

from reconstruction.errors import InputError

# The record each command writes at the top of its output folder: a folder holding one is an image2sim output.
MARKER_FILES = (
    "reconstruct.json",
    "scene.json",
    "diagnosis.json",
    "calibration.json",
    "residual.json",
    "track.json",
    "variants.json",
    "property_net.json",
    "rollout.json",
)


def check_outside_inputs(
    out_dir: str | Path, inputs: Iterable[str | Path | None], *, error: type[Exception] = InputError
) -> None:
    """Refuses an output folder that is one of the inputs or holds one: replacing it would delete that input.

    Raises:
        `error` (InputError unless given): `out_dir` is an input (file or folder) or a folder above one.
    """
    out = Path(out_dir).resolve()
    for given in inputs:
        if given is None:
            continue
        src = Path(given).resolve()
        if src == out or out in src.parents:
            relation = "is" if src == out else "holds"
            raise error(
                f"output folder {out_dir} {relation} the input {given}; choose an output folder outside the inputs"
            )


def check_output_dir(
    out_dir: str | Path,
    *,
    overwrite: bool = False,
    error: type[Exception] = InputError,
    inputs: Iterable[str | Path | None] = (),
    offers_overwrite: bool = True,
) -> None:
    """What `staged_output_dir` checks before any work, for callers that want to fail before long work.

    `offers_overwrite=False`: the command has no --overwrite, so the error does not suggest one.

    Raises:
        `error` (InputError unless given): `out_dir` exists, is not empty, and `overwrite` is False, or it is not an
        image2sim output (holds none of `MARKER_FILES`); it is a file, a symbolic link or a mount point; or it is or
        holds one of `inputs`.
    """
    out_dir = Path(out_dir)
    inputs = tuple(inputs)  # read twice below
    check_outside_inputs(out_dir, inputs, error=error)
    if out_dir.is_symlink():  # replacing the output would replace the link, or write through it into its target
        raise error(f"output {out_dir} is a symbolic link; pass the folder's real path (-o), or a new folder")
    if out_dir.exists() and not out_dir.is_dir():
        raise error(f"output {out_dir} is a file; pass a folder path (-o)")
    if out_dir.is_dir() and os.path.ismount(out_dir):  # a result moves in by renaming, and a mount point cannot move
        raise error(
            f"output folder {out_dir} is a mount point, which cannot be replaced by the result; pass a new folder "
            f"inside it (-o {out_dir / 'out'})"
        )
    # A probe beside the output: a location it cannot be written to (a read-only or virtual file system, a file in
    # the path) fails before the work rather than after it.
    probe, created = _mkdir_beside(Path(os.path.abspath(out_dir)), "probe", error)
    probe.rmdir()
    _remove_empty(created)
    if out_dir.is_dir() and any(out_dir.iterdir()):
        if overwrite:
            if not _is_image2sim_output(out_dir):  # a mistyped -o with --overwrite would delete someone's folder
                raise error(_not_replaceable(out_dir, inputs))
        else:
            what_to_do = (
                "pass --overwrite (Python: overwrite=True) or another output folder"
                if offers_overwrite
                else "choose a new or empty output folder"
            )
            raise error(f"output folder {out_dir} already exists and is not empty; {what_to_do}")


def _mkdir_beside(out_dir: Path, tag: str, error: type[Exception]) -> tuple[Path, list[Path]]:
    """A new hidden folder `.{name}.{tag}-{random}` beside the absolute `out_dir`, its parents made as needed (with
    `mkdir`, so it has the user's usual permissions). Returns it and the parents it created, deepest first.

    Raises:
        `error`: the folder cannot be made there (nothing created is left behind).
    """
    created = [p for p in (out_dir.parent, *out_dir.parent.parents) if not p.exists()]
    try:
        out_dir.parent.mkdir(parents=True, exist_ok=True)
        folder = out_dir.with_name(f".{out_dir.name or 'out'}.{tag}-{secrets.token_hex(4)}")
        folder.mkdir()
    except OSError as exc:
        _remove_empty(created)
        in_the_way = next((p for p in out_dir.parents if p.exists() and not p.is_dir()), None)
        if in_the_way is not None:  # mkdir says "File exists", which reads as if the output folder did
            raise error(
                f"cannot create the output folder {out_dir}: {in_the_way} is a file, not a folder; choose another -o"
            ) from exc
        raise error(f"cannot create the output folder {out_dir} ({exc.strerror or exc}); choose another -o") from exc
    return folder, created


def _is_image2sim_output(folder: Path) -> bool:
    """The folder holds one of the records each command writes at the top of its output (`MARKER_FILES`)."""
    return any((folder / marker).is_file() for marker in MARKER_FILES)


def _not_replaceable(out_dir: Path, inputs: Iterable[str | Path | None]) -> str:
    """Why --overwrite will not replace ``out_dir``, a non-empty folder that is no image2sim output: inside an input
    folder (a scene's `assets/`, say) it would delete part of that input; elsewhere, someone's folder."""
    out = out_dir.resolve()
    for given in inputs:
        if given is not None and Path(given).is_dir() and Path(given).resolve() in out.parents:
            return (
                f"output folder {out_dir} lies inside the input {given} and is not an image2sim output, so "
                "--overwrite would delete part of the input; choose an output folder outside the inputs"
            )
    return (
        f"output folder {out_dir} is not empty and is not an image2sim output (it holds none of "
        f"{', '.join(MARKER_FILES)}), so --overwrite will not replace it; choose a new folder (-o), or empty this one "
        "yourself"
    )


@contextmanager
def staged_output_dir(
    out_dir: Path,
    *,
    overwrite: bool = False,
    error: type[Exception] = InputError,
    inputs: Iterable[str | Path | None] = (),
) -> Iterator[Path]:
    """Yields a temporary folder next to `out_dir`, moved into place only if the block succeeds.

    An existing non-empty `out_dir` is replaced only with `overwrite=True`, and then only once the new result is
    complete: a failure leaves the user's previous folder untouched and no partial output behind. `out_dir` may not
    be one of `inputs` nor hold one (`check_outside_inputs`), overwrite or not.

    Raises:
        `error` (InputError unless given): `out_dir` exists, is not empty, and `overwrite` is False; it is a file; or
        it is or holds one of `inputs`.
    """
    check_output_dir(out_dir, overwrite=overwrite, error=error, inputs=inputs)
    out_dir = Path(os.path.abspath(out_dir))  # `-o .` has no name to stage beside; links are refused, not followed
    staging, created = _mkdir_beside(out_dir, "partial", error)  # `created` is removed again on failure
    try:
        yield staging
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        _remove_empty(created)
        raise
    backup = None
    try:
        if out_dir.exists():
            backup = out_dir.with_name(f".{out_dir.name}.old-{staging.name.rsplit('-', 1)[-1]}")
            out_dir.rename(backup)
        staging.rename(out_dir)
    except OSError as exc:
        # The folder cannot move (made immutable, busy, or created by someone else meanwhile): the user's folder
        # goes back, and the finished result is kept where it is, named, rather than thrown away.
        if backup is not None and not out_dir.exists():
            backup.rename(out_dir)
        raise error(
            f"cannot move the result into {out_dir} ({exc.strerror or exc}); it is kept, complete, in {staging}: "
            "move it where you want it, or re-run with another output folder (-o)"
        ) from exc
    except BaseException:  # interrupted: put the user's folder back, leave nothing half-made
        if backup is not None and not out_dir.exists():
            backup.rename(out_dir)
        shutil.rmtree(staging, ignore_errors=True)
        raise
    if backup is not None:
        shutil.rmtree(backup, ignore_errors=True)


@contextmanager
def atomic_file(path: Path, mode: str = "wb") -> Iterator[IO[Any]]:
    """A file that appears at ``path`` whole or not at all: written under a hidden temporary name beside it (one
    that does not end in ``path``'s suffix, so no folder listing picks it up), flushed to disk and renamed over
    ``path`` once the ``with`` body ends; removed on any error, and a removal that fails too (a read-only folder)
    does not hide the write's own error. ``mode`` is ``"wb"`` or ``"w"`` (UTF-8 text); the file gets 0o666 less the
    umask, as ``open`` gives."""
    if mode not in ("wb", "w"):
        raise ValueError(f"mode {mode!r}; expected 'wb' or 'w'")
    tmp = path.with_name(f".{path.name}.{secrets.token_hex(6)}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    try:
        with os.fdopen(fd, mode, encoding=None if mode == "wb" else "utf-8") as handle:
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)
        raise


def write_image(
    path: Path, image: np.ndarray, params: Sequence[int] = (), *, error: type[Exception] = InputError
) -> None:
    """``cv2.imwrite`` that fails loudly: OpenCV returns False on a full disk or an unwritable folder, and the run
    would go on to fail later somewhere that does not say why.

    Raises:
        `error` (InputError unless given): the image could not be written.
    """
    import cv2

    if not cv2.imwrite(str(path), image, list(params)):
        raise error(
            f"could not write {path} (disk full, or the folder not writable?); free some space or choose "
            "another output folder (-o)"
        )


def _remove_empty(folders: list[Path]) -> None:
    """Removes the folders (deepest first) that were created for an output that did not come to be."""
    for folder in folders:
        try:
            folder.rmdir()
        except OSError:
            return
