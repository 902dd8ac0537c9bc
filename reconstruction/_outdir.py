"""Output folders that appear whole or not at all."""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from reconstruction.errors import InputError

MARKER_FILES = ("reconstruct.json", "scene.json", "diagnosis.json", "calibration.json")


@contextmanager
def staged_output_dir(out_dir: Path, *, overwrite: bool = False, error: type[Exception] = InputError) -> Iterator[Path]:
    """Yields a temporary folder next to `out_dir`, moved into place only if the block succeeds.

    An existing non-empty `out_dir` is replaced only with `overwrite=True`, and then only once the new result is
    complete: a failure leaves the user's previous folder untouched and no partial output behind.

    Raises:
        `error` (InputError unless given): `out_dir` exists, is not empty, and `overwrite` is False; or it is a file.
    """
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise error(f"output {out_dir} is a file; pass a folder path (-o)")
    if out_dir.is_dir() and any(out_dir.iterdir()) and not overwrite:
        raise error(
            f"output folder {out_dir} already exists and is not empty; pass --overwrite (Python: overwrite=True) or"
            " another output folder"
        )
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.partial-", dir=out_dir.parent))
    try:
        yield staging
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    backup = None
    if out_dir.exists():
        backup = out_dir.with_name(f".{out_dir.name}.old-{staging.name.rsplit('-', 1)[-1]}")
        out_dir.rename(backup)
    staging.rename(out_dir)
    if backup is not None:
        shutil.rmtree(backup, ignore_errors=True)
