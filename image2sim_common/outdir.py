"""Output folders that appear whole or not at all."""

from __future__ import annotations

import atexit
import contextlib
import errno
import fcntl
import hashlib
import logging
import os
import re
import secrets
import shutil
import tempfile
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any

import numpy as np

log = logging.getLogger(__name__)

# The record each command writes at the top of its output folder: a folder holding one is an image2sim output. Each
# package registers its own commands' records when it is imported (`register_record_files`); `grounder`, which runs
# every command, imports the other two packages first, so all of them are known whenever a command runs.
_RECORD_FILES: list[str] = []


def register_record_files(*names: str) -> None:
    """Adds the records (file names) that a package's commands write at the top of their output folders."""
    for name in names:
        if name not in _RECORD_FILES:
            _RECORD_FILES.append(name)


def check_outside_inputs(out_dir: str | Path, inputs: Iterable[str | Path | None], *, error: type[Exception]) -> None:
    """Refuses an output folder that is one of the inputs or holds one: replacing it would delete that input.

    Raises:
        `error`: `out_dir` is an input (file or folder) or a folder above one.
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
    error: type[Exception],
    inputs: Iterable[str | Path | None] = (),
    offers_overwrite: bool = True,
) -> None:
    """What `staged_output_dir` checks before any work, for callers that want to fail before long work.

    It also claims the folder for this process (`claim_output`): a second run on it is refused from then on, until
    `staged_output_dir` has moved the result in, `release_output_claims` is called, or the process ends.
    `offers_overwrite=False`: the command has no --overwrite, so the error does not suggest one.

    Raises:
        `error`: `out_dir` exists, is not empty, and `overwrite` is False, or it is not an image2sim output (holds
        none of the records registered with `register_record_files`); it is a file, a symbolic link or a mount point;
        it is or holds one of `inputs`; or another image2sim run is writing it.
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
    absolute = Path(os.path.abspath(out_dir))
    probe, created = _mkdir_beside(absolute, "probe", error)
    probe.rmdir()
    try:
        claim_output(absolute, error=error)
    except BaseException:
        _remove_empty(created)
        raise
    _claims[absolute].created.extend(created)  # removed again if no output comes to be
    try:
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
    except BaseException:
        _release(absolute)
        raise


# Names beside an output folder `NAME` (all hidden, all short whatever NAME's length, so a name the file system
# allows is never refused for ours): `.i2s-KEY.lock` (the claim), `.i2s-KEY-RANDOM.partial` (a run's staging),
# `.i2s-KEY-RANDOM.old` (the replaced output, for the instant of the swap) and `.i2s-KEY-RANDOM.probe`, where KEY is
# a hash of NAME's bytes.
_STAGE_PREFIX = ".i2s-"
_STAGE_TAGS = ("partial", "probe", "old")


def _is_stage_name(name: str) -> bool:
    """`name` is one of a run's folders beside an output (staging, swap, probe)."""
    return name.startswith(_STAGE_PREFIX) and name.rsplit(".", 1)[-1] in _STAGE_TAGS


def is_bookkeeping_name(name: str) -> bool:
    """A name image2sim gives its own entries beside an output (claim, staging, swap, probe): never user data, never
    to be copied along with a folder that holds an output being written."""
    return _is_stage_name(name) or (name.startswith(_STAGE_PREFIX) and name.endswith(".lock"))


def _key(out_dir: Path) -> str:
    return hashlib.sha256(os.fsencode(out_dir.name)).hexdigest()[:12]


def _lock_path(out_dir: Path) -> Path:
    return out_dir.with_name(f"{_STAGE_PREFIX}{_key(out_dir)}.lock")


class _Claim:
    """An exclusive `flock` on `.i2s-KEY.lock` beside an output folder, held by this process while it writes there.

    The kernel drops the lock when the process ends, however it ends (SIGKILL too), so a lock file without a holder
    marks a dead run: the next run takes it over and removes what that run left (`_clean_stale`)."""

    def __init__(self, out_dir: Path, fd: int) -> None:
        self.out_dir = out_dir
        self.fd = fd
        self.depth = 1
        self.created: list[Path] = []  # parent folders made for the output, deepest first

    def release(self, *, whole: bool = False) -> None:
        """One hold fewer (`whole`: every hold); the lock and its file go with the last."""
        self.depth = 0 if whole else self.depth - 1
        if self.depth > 0:
            return
        _claims.pop(self.out_dir, None)
        with contextlib.suppress(OSError):  # unlinked while held: a run that opened it meanwhile sees it stale
            os.unlink(_lock_path(self.out_dir))
        with contextlib.suppress(OSError):
            os.close(self.fd)
        _remove_empty(self.created)  # stops at the first that is not empty (the output's, once it is there)


_claims: dict[Path, _Claim] = {}


def claim_output(out_dir: str | Path, *, error: type[Exception]) -> None:
    """Claims `out_dir` (made absolute) for this process; a claim already held here is held once more.

    Taking over a dead run's claim removes that run's staging folders and probes, and puts back an output that run
    had moved aside at its final swap and not yet replaced.

    Raises:
        `error`: another process holds the claim: another image2sim run is writing to `out_dir`.
    """
    out_dir = Path(os.path.abspath(out_dir))
    held = _claims.get(out_dir)
    if held is not None:
        held.depth += 1
        return
    lock = _lock_path(out_dir)
    while True:
        try:
            fd = os.open(lock, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        except OSError as exc:
            raise error(
                f"cannot create the output folder {out_dir} ({exc.strerror or exc}); choose another -o"
            ) from exc
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _read_holder(fd)
            os.close(fd)
            raise error(
                f"another image2sim run{holder} is writing to {out_dir}; wait for it to finish, or choose another "
                "output folder (-o)"
            ) from None
        try:
            same = os.fstat(fd).st_ino == os.stat(lock).st_ino
        except FileNotFoundError:  # released (and unlinked) by its holder between our open and our lock
            same = False
        if same:
            break
        os.close(fd)
    with contextlib.suppress(OSError):
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
    _claims[out_dir] = _Claim(out_dir, fd)
    _clean_stale(out_dir)


def _read_holder(fd: int) -> str:
    with contextlib.suppress(OSError, ValueError):
        pid = int(os.pread(fd, 32, 0).decode().strip())
        return f" (process {pid})"
    return ""


def _release(out_dir: Path) -> None:
    held = _claims.get(out_dir)
    if held is not None:
        held.release()


def release_output_claims() -> None:
    """Releases every output claim this process holds (a command that checked its output and then stopped)."""
    for claim in list(_claims.values()):
        claim.release(whole=True)


atexit.register(release_output_claims)


def _stale_siblings(out_dir: Path) -> list[Path]:
    prefix = f"{_STAGE_PREFIX}{_key(out_dir)}-"
    # The names earlier versions gave their staging folders (`.NAME.partial-RANDOM`), which nothing cleaned.
    legacy = re.compile(re.escape(f".{out_dir.name}.") + r"(partial|probe|old)-[0-9a-f]{8}")
    found = []
    try:
        entries = list(out_dir.parent.iterdir())
    except OSError:
        return []
    for entry in entries:
        name = entry.name
        ours = name.startswith(prefix) and _is_stage_name(name)
        if (ours or legacy.fullmatch(name)) and entry.is_dir() and not entry.is_symlink():
            found.append(entry)
    return found


def _clean_stale(out_dir: Path) -> None:
    """What a dead run on `out_dir` left beside it, removed; called with the claim held, so no live run owns any of
    it. An output it had moved aside (`.old`) and not replaced is put back first."""
    for folder in _stale_siblings(out_dir):
        is_backup = folder.name.endswith(".old") or ".old-" in folder.name
        if is_backup and not os.path.lexists(out_dir):
            with contextlib.suppress(OSError):
                folder.rename(out_dir)
                log.warning("put back %s, which an interrupted run had moved aside", out_dir)
                continue
        shutil.rmtree(folder, ignore_errors=True)


def _mkdir_beside(out_dir: Path, tag: str, error: type[Exception]) -> tuple[Path, list[Path]]:
    """A new hidden folder `.i2s-KEY-RANDOM.TAG` beside the absolute `out_dir`, its parents made as needed (with
    `mkdir`, so it has the user's usual permissions). Returns it and the parents it created, deepest first.

    Raises:
        `error`: the folder cannot be made there (nothing created is left behind).
    """
    created = [p for p in (out_dir.parent, *out_dir.parent.parents) if not p.exists()]
    try:
        out_dir.parent.mkdir(parents=True, exist_ok=True)
        folder = out_dir.with_name(f"{_STAGE_PREFIX}{_key(out_dir)}-{secrets.token_hex(4)}.{tag}")
        folder.mkdir()
    except OSError as exc:
        _remove_empty(created)
        in_the_way = next((p for p in out_dir.parents if p.exists() and not p.is_dir()), None)
        if in_the_way is not None:  # mkdir says "File exists", which reads as if the output folder did
            raise error(
                f"cannot create the output folder {out_dir}: {in_the_way} is a file, not a folder; choose another -o"
            ) from exc
        if exc.errno == errno.ENOSPC:
            raise error(f"cannot create the output folder {out_dir}: {no_space_advice(out_dir)}") from exc
        raise error(f"cannot create the output folder {out_dir} ({exc.strerror or exc}); choose another -o") from exc
    return folder, created


def _in_staging(path: str | Path) -> bool:
    return any(map(_is_stage_name, Path(path).parts))


def _existing(path: str | Path) -> Path:
    """The folder a user knows for `path`: above any staging folder (theirs is the one holding the output), and the
    deepest part of it that exists."""
    where = Path(path)
    for i, part in enumerate(where.parts):
        if _is_stage_name(part):
            where = Path(*where.parts[:i])
            break
    while not where.exists() and where != where.parent:
        where = where.parent
    return where


def no_space_advice(path: str | Path) -> str:
    """What to tell a user whose disk filled while writing under `path`: where, and what to do."""
    where = _existing(path)
    return (
        f"no space left on the disk that holds {where}; free some space there (see `df -h {where}`) or choose an "
        "output folder on another disk (-o), then run again"
    )


def require_free_space(folder: str | Path, need_bytes: int, what: str, *, error: type[Exception]) -> None:
    """Refuses, before it starts, work that writes about `need_bytes` under `folder` where the disk has less free:
    for native code (COLMAP) that aborts the process, rather than raising, when a write fails.

    Raises:
        `error`: the disk that holds `folder` has less than `need_bytes` free.
    """
    where = _existing(folder)
    try:
        free = shutil.disk_usage(where).free
    except OSError:  # cannot tell: let the work try
        return
    if free < need_bytes:
        raise error(
            f"{what} needs about {need_bytes / 1e6:.0f} MB free, and the disk that holds {where} has "
            f"{free / 1e6:.0f} MB; free some space there (see `df -h {where}`) or choose an output folder on another "
            "disk (-o)"
        )


def _is_image2sim_output(folder: Path) -> bool:
    """The folder holds one of the records each command writes at the top of its output (`register_record_files`)."""
    return any((folder / marker).is_file() for marker in _RECORD_FILES)


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
        f"{', '.join(_RECORD_FILES)}), so --overwrite will not replace it; choose a new folder (-o), or empty this one "
        "yourself"
    )


@contextmanager
def staged_output_dir(
    out_dir: Path,
    *,
    overwrite: bool = False,
    error: type[Exception],
    inputs: Iterable[str | Path | None] = (),
) -> Iterator[Path]:
    """Yields a temporary folder next to `out_dir`, moved into place only if the block succeeds.

    An existing non-empty `out_dir` is replaced only with `overwrite=True`, and then only once the new result is
    complete: a failure leaves the user's previous folder untouched and no partial output behind. `out_dir` may not
    be one of `inputs` nor hold one (`check_outside_inputs`), overwrite or not. The run holds `out_dir`'s claim
    (`claim_output`) from the check to the end, so a second run on the same folder is refused; at the final move the
    folder is looked at again, and what appeared there meanwhile is replaced only if it is empty, or an image2sim
    output with `overwrite`: anything else stays as it is, and the result is kept beside it under a name of its own.

    Raises:
        `error`: `out_dir` exists, is not empty, and `overwrite` is False; it is a file; it
        is or holds one of `inputs`; another run is writing it; or something appeared there that may not be replaced.
    """
    check_output_dir(out_dir, overwrite=overwrite, error=error, inputs=inputs)
    out_dir = Path(os.path.abspath(out_dir))  # `-o .` has no name to stage beside; links are refused, not followed
    claim = _claims[out_dir]
    try:
        staging, _ = _mkdir_beside(out_dir, "partial", error)  # the parent exists: the claim made it, and removes it
        try:
            with _reachable_by_native_code(staging) as native_staging:
                yield native_staging
        except BaseException:
            shutil.rmtree(staging, ignore_errors=True)
            raise
        _move_into_place(staging, out_dir, overwrite=overwrite, error=error)
    finally:
        claim.release(whole=True)  # also where `check_output_dir` claimed it before: the output is in place or given up


def _move_into_place(staging: Path, out_dir: Path, *, overwrite: bool, error: type[Exception]) -> None:
    """The finished `staging` renamed to `out_dir`. What is at `out_dir` now is looked at afresh (it may have appeared
    or changed during the run): an empty folder is replaced, an image2sim output only with `overwrite`, anything
    else never; then the result is kept, renamed to a visible folder beside it, and the error says where."""
    if os.path.lexists(out_dir):
        empty = out_dir.is_dir() and not out_dir.is_symlink() and not any(out_dir.iterdir())
        replaceable = overwrite and out_dir.is_dir() and not out_dir.is_symlink() and _is_image2sim_output(out_dir)
        if not (empty or replaceable):
            kept = _keep_result(staging, out_dir)
            if not out_dir.is_dir() or out_dir.is_symlink():
                what = f"something that is not a folder appeared at {out_dir} while this run worked"
            elif overwrite:
                what = f"{out_dir} changed while this run worked and is no longer an image2sim output"
            else:
                what = f"a folder {out_dir}, not empty, appeared while this run worked"
            raise error(
                f"{what}; it was left as it is, and the result is kept, complete, in {kept}: move it where you want it"
            )
    backup = None
    try:
        if os.path.lexists(out_dir):
            backup = staging.with_name(staging.name.removesuffix(".partial") + ".old")
            out_dir.rename(backup)
        staging.rename(out_dir)
    except OSError as exc:
        # The folder cannot move (made immutable, busy, or created by someone else meanwhile): the user's folder
        # goes back, and the finished result is kept, renamed out of the staging names, rather than thrown away.
        if backup is not None and not os.path.lexists(out_dir):
            backup.rename(out_dir)
        kept = _keep_result(staging, out_dir)
        raise error(
            f"cannot move the result into {out_dir} ({exc.strerror or exc}); it is kept, complete, in {kept}: "
            "move it where you want it, or re-run with another output folder (-o)"
        ) from exc
    except BaseException:  # interrupted: put the user's folder back, leave nothing half-made
        if backup is not None and not os.path.lexists(out_dir):
            backup.rename(out_dir)
        shutil.rmtree(staging, ignore_errors=True)
        raise
    if backup is not None:
        shutil.rmtree(backup, ignore_errors=True)


def _keep_result(staging: Path, out_dir: Path) -> Path:
    """The finished result, renamed from its staging name (which a later run would clean as stale) to a visible
    `NAME.image2sim-RANDOM` beside `out_dir` (NAME shortened as the file system's name limit needs)."""
    suffix = f".image2sim-{secrets.token_hex(3)}"
    name = os.fsencode(out_dir.name)[: 255 - len(suffix)]
    kept = out_dir.with_name(os.fsdecode(name) + suffix)
    try:
        staging.rename(kept)
    except OSError:
        return staging
    return kept


@contextmanager
def _reachable_by_native_code(folder: Path) -> Iterator[Path]:
    """`folder`, or where its path is not UTF-8 (a name in another encoding: any bytes but '/' are allowed), a
    symbolic link to it under a UTF-8 temporary path: OpenCV, COLMAP and MuJoCo take paths as UTF-8 strings, and
    crash or refuse on others."""
    if is_utf8_path(folder):
        yield folder
        return
    link_dir = Path(tempfile.mkdtemp(prefix="image2sim-"))
    link = link_dir / "out"
    try:
        os.symlink(folder, link)
        yield link
    finally:
        shutil.rmtree(link_dir, ignore_errors=True)


def is_utf8_path(path: str | Path) -> bool:
    """The path's bytes are UTF-8, as the native libraries need (Python keeps other bytes as lone surrogates)."""
    try:
        os.fspath(path).encode("utf-8")
    except UnicodeEncodeError:
        return False
    return True


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


def write_text_atomic(path: Path, text: str) -> Path:
    """Writes ``text`` (UTF-8) to ``path`` whole or not at all (`atomic_file`). Returns ``path``."""
    path = Path(path)
    with atomic_file(path, "w") as handle:
        handle.write(text)
    return path


def write_image(path: Path, image: np.ndarray, params: Sequence[int] = (), *, error: type[Exception]) -> None:
    """``cv2.imwrite`` that fails loudly: OpenCV returns False on a full disk or an unwritable folder, and the run
    would go on to fail later somewhere that does not say why.

    Raises:
        `error`: the image could not be written.
    """
    import cv2

    if not cv2.imwrite(str(path), image, list(params)):
        try:
            full = shutil.disk_usage(_existing(path)).free < image.nbytes + 2**20
        except OSError:
            full = False
        shown = path.name if _in_staging(path) else str(path)  # a staging folder is no name the user knows
        if full:
            raise error(f"could not write {shown}: {no_space_advice(path)}")
        raise error(
            f"could not write {shown} (disk full, or the folder {_existing(path)} not writable, or not an image "
            "type: .png or .jpg?); free some space or choose another output folder (-o)"
        )


def _remove_empty(folders: list[Path]) -> None:
    """Removes the folders (deepest first) that were created for an output that did not come to be."""
    for folder in folders:
        try:
            folder.rmdir()
        except OSError:
            return
