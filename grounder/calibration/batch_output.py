"""A batch calibration's output folder (its layout: the `grounder.calibration.batch` module docstring): the
fingerprints of what a job reads (`job_inputs`), the per-job result records (`results/<id>.json`) and when one is
still the job's result (`stale_reason`), the ``batch.json`` marker and the check of the folder
(`check_batch_output`), and the table of all jobs (``results.csv``, ``results.json``).
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

from grounder.calibration.batch_jobs import Job
from grounder.errors import GrounderError, shown
from image2sim_common.outdir import write_text_atomic

RESULTS_DIR = "results"
SCENES_DIR = "scenes"
MARKER = "batch.json"
MARKER_FORMAT = "image2sim-batch/1"


# A job's inputs, fingerprinted so that a re-run can tell a finished job from one whose inputs were edited since.
# Each is a sha256 hex digest; MISSING stands for a path that is not there (the job then fails, or is refused).
INPUT_KINDS = ("settings", "scene", "trajectories")
MISSING = "missing"
_BLOCK = 1 << 20


def _file_sha256(path: Path) -> str:
    """sha256 of a file's bytes, read in 1 MiB blocks; MISSING, or why it cannot be read, in place of one."""
    digest = hashlib.sha256()
    try:
        with path.open("rb") as handle:
            for block in iter(lambda: handle.read(_BLOCK), b""):
                digest.update(block)
    except FileNotFoundError:
        return MISSING
    except OSError as exc:
        return f"unreadable ({exc.strerror or exc})"
    return digest.hexdigest()


def _files_sha256(base: Path, names: Iterable[str], *, note: str = "") -> str:
    """One sha256 over the names (relative to ``base``, POSIX) and contents of files, in sorted order."""
    digest = hashlib.sha256(note.encode())
    for name in sorted(set(names)):
        digest.update(f"{name}\0{_file_sha256(base / name)}\n".encode())
    return digest.hexdigest()


def _top_level_files(folder: Path) -> list[str]:
    try:
        return [p.name for p in folder.iterdir() if p.is_file()]
    except OSError:
        return []


def settings_sha256(settings: Mapping[str, Any]) -> str:
    """sha256 of a job's settings as canonical JSON (sorted keys, no spaces)."""
    text = json.dumps(dict(settings), sort_keys=True, separators=(",", ":"), ensure_ascii=False, default=str)
    return hashlib.sha256(text.encode()).hexdigest()


def scene_sha256(scene: Path) -> str:
    """sha256 of the files a scene is read from: the MJCF and every file it includes or loads
    (`grounder.sim.scene_files.scene_files`: meshes, textures, included MJCF), and for a scene folder also its other
    top-level files (``scene.json``, which embedding mode reads). MISSING when ``scene`` is not there."""
    from grounder.sim.scene_files import SCENE_XML, scene_files

    if not scene.exists():
        return MISSING
    xml = scene / SCENE_XML if scene.is_dir() else scene
    names = _top_level_files(scene) if scene.is_dir() else [scene.name]
    note = ""
    try:
        names += [rel.as_posix() for rel in scene_files(xml)]
    except GrounderError as exc:  # not XML, or names a file outside its folder: the job fails on it
        note = f"unusable: {exc}"
    return _files_sha256(xml.parent, names, note=note)


def trajectories_sha256(folder: Path, fmt: str | None) -> str:
    """sha256 of a trajectory folder's top-level files (names and contents) and its ``format``; with a format also
    of the files one folder down, where an importer may read them (dair-pll-cube: ``tosses/N.pt``), except in a
    batch output placed there. MISSING when ``folder`` is not a folder.

    Only what a reader could take is hashed: a folder's top level (every command reads its inputs' top level only),
    so an output written inside the folder later (``-o data/out``) does not count as a change.
    """
    if not folder.is_dir():
        return MISSING
    names = _top_level_files(folder)
    if fmt is not None:
        try:
            subs = [p for p in folder.iterdir() if p.is_dir() and not (p / MARKER).exists()]
        except OSError:
            subs = []
        for sub in subs:
            names += [f"{sub.name}/{name}" for name in _top_level_files(sub)]
    return _files_sha256(folder, names, note=f"format={fmt}")


def job_inputs(
    job: Job, *, seen_here: bool = True, memo: dict[tuple[object, ...], str] | None = None
) -> dict[str, Any]:
    """The fingerprints of what ``job`` reads, by kind (:data:`INPUT_KINDS`), as its result record keeps them.

    Args:
        job: The job.
        seen_here: False on a driver that only submits to a cluster: a scene or trajectory path that is not there
            gets None (not compared), since the paths need only exist on the cluster's nodes.
        memo: Digests already computed in this pass, by path (the jobs of a matrix share scenes and folders).
    """
    memo = {} if memo is None else memo

    def cached(key: tuple[object, ...], compute: Callable[[], str]) -> str | None:
        if key not in memo:
            memo[key] = compute()
        return None if memo[key] == MISSING and not seen_here else memo[key]

    return {
        "settings": settings_sha256(job.settings),
        "scene": cached(("scene", job.scene), lambda: scene_sha256(job.scene)),
        "trajectories": cached(
            ("trajectories", job.trajectories, job.format), lambda: trajectories_sha256(job.trajectories, job.format)
        ),
    }


def stale_reason(record: Mapping[str, Any], inputs: Mapping[str, Any]) -> str | None:
    """Why ``record`` is not the result of the job as it is now (``inputs``: :func:`job_inputs`), or None.

    An input that is None in ``inputs`` (not visible here) is not compared.
    """
    recorded = record.get("inputs")
    if not isinstance(recorded, Mapping):
        return "its result has no fingerprint of its inputs (recorded by an older image2sim)"
    changed = [kind for kind in INPUT_KINDS if inputs.get(kind) is not None and recorded.get(kind) != inputs[kind]]
    if not changed:
        return None
    return f"{' and '.join(changed)} changed"


def _write_json_atomic(path: Path, payload: object) -> None:
    from image2sim_common.outdir import atomic_file

    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_file(path, "w") as handle:
        handle.write(json.dumps(payload, indent=1) + "\n")


def result_path(out_dir: Path, job_id: str) -> Path:
    return Path(out_dir) / RESULTS_DIR / f"{job_id}.json"


def _is_number(value: object) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _record_problem(data: object, job_id: str) -> str | None:
    """What makes ``data`` unusable as the result record of ``job_id`` (None: nothing); checks what the table reads."""
    if not isinstance(data, dict):
        return f"not a JSON object but {type(data).__name__}"
    if data.get("id") != job_id:
        return f"'id' is {shown(data.get('id'))}, not {shown(job_id)}"
    if data.get("status") not in ("ok", "failed"):
        return f'\'status\' is {shown(data.get("status"))}, not "ok" or "failed"'
    if "seconds" in data and not _is_number(data["seconds"]):
        return f"'seconds' is {shown(data['seconds'])}, not a number"
    if not isinstance(data.get("error"), (str, type(None))):
        return f"'error' is {shown(data['error'])}, not text"
    inputs = data.get("inputs")
    if "inputs" in data and not (
        isinstance(inputs, dict) and all(isinstance(inputs.get(k), (str, type(None))) for k in INPUT_KINDS)
    ):
        return "'inputs' is not a mapping of settings, scene and trajectories to fingerprints (text)"
    parameters = data.get("parameters")
    if parameters and not (
        isinstance(parameters, dict) and all(isinstance(k, str) and _is_number(v) for k, v in parameters.items())
    ):
        return "'parameters' is not a mapping of names to numbers"
    errors = data.get("errors") or {}
    if not isinstance(errors, dict):
        return "'errors' is not a mapping"
    for when in ("before", "after"):
        side = errors.get(when, {})
        if not isinstance(side, dict):
            return f"'errors.{when}' is not a mapping"
        for split in ("train", "validation"):
            if split in side and not (
                isinstance(side[split], dict)
                and _is_number(side[split].get("position_pct"))
                and (split == "train" or _is_number(side[split].get("rotation_deg")))
            ):
                return f"'errors.{when}.{split}' lacks numeric position_pct / rotation_deg"
    return None


def _load_result(out_dir: Path, job_id: str) -> tuple[dict[str, Any] | None, str | None]:
    """``(record, None)``; ``(None, None)`` when the job has no record; ``(None, why)`` for an unusable one."""
    path = result_path(out_dir, job_id)
    if not path.exists() and not path.is_symlink():
        return None, None
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        return None, f"cannot be read ({exc.strerror or exc})"
    except ValueError as exc:  # not UTF-8
        return None, f"not JSON ({exc})"
    try:
        data = json.loads(text)
    except ValueError as exc:
        return None, f"not JSON ({exc})"
    except RecursionError:
        return None, "not a result record (JSON nested too deeply)"
    problem = _record_problem(data, job_id)
    return (None, problem) if problem else (data, None)


def read_result(out_dir: Path, job_id: str) -> dict[str, Any] | None:
    """A job's result record, or None if it has none (or an unreadable or invalid one: the job counts as pending)."""
    return _load_result(out_dir, job_id)[0]


def current_result(out_dir: Path, job: Job, inputs: Mapping[str, Any]) -> dict[str, Any] | None:
    """``job``'s result record if it is the result of the job as it is now (``inputs``: :func:`job_inputs`)."""
    record = read_result(out_dir, job.id)
    return record if record is not None and stale_reason(record, inputs) is None else None


def _is_marker(path: Path) -> bool:
    if path.is_symlink() or not path.is_file():
        return False
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError):  # RecursionError: JSON nested too deeply
        return False
    return isinstance(data, dict) and data.get("format") == MARKER_FORMAT


def check_batch_output(out_dir: Path) -> None:
    """Refuses an output folder that :func:`run_batch` must not write into; creates nothing.

    A batch run deletes stale ``scenes/<id>`` folders and temporary files and rewrites the tables, so it writes only
    into a new or empty folder, or into the output of an earlier batch run (marked by ``batch.json``) to resume it.

    Raises:
        GrounderError: ``out_dir`` is a symbolic link, a file, an unreadable folder, or a non-empty folder without
            the marker; or the marked folder's ``results``/``scenes`` is not a real folder.
    """
    out_dir = Path(out_dir)
    if out_dir.is_symlink():
        raise GrounderError(f"output {out_dir} is a symbolic link; pass the folder it points to, or a new folder (-o)")
    if not out_dir.exists():
        return
    if not out_dir.is_dir():
        raise GrounderError(f"output {out_dir} is a file; pass a folder path (-o)")
    try:
        empty = not any(out_dir.iterdir())
    except OSError as exc:
        raise GrounderError(f"output folder {out_dir} cannot be read ({exc.strerror}); choose another folder") from exc
    if empty:
        return
    if not _is_marker(out_dir / MARKER):
        raise GrounderError(
            f"output folder {out_dir} is not empty and is not the output of an image2sim batch run (no valid "
            f"{MARKER} in it), and a run would replace files there; choose a new or empty folder (-o)"
        )
    for name in (RESULTS_DIR, SCENES_DIR):
        sub = out_dir / name
        if sub.is_symlink() or (sub.exists() and not sub.is_dir()):
            raise GrounderError(
                f"{sub} is not a folder written by image2sim batch (a link or a file); choose a new output folder (-o)"
            )


def _prepare_output(out_dir: Path, jobs: Sequence[Job]) -> None:
    """Checks ``out_dir`` (:func:`check_batch_output`), then creates it with its marker and subfolders."""
    check_batch_output(out_dir)
    for job in jobs:
        record = result_path(out_dir, job.id)
        if record.is_dir() and not record.is_symlink():
            raise GrounderError(
                f"{record} is a folder where batch writes job {job.id}'s result record; move it away and re-run"
            )
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        if not _is_marker(out_dir / MARKER):
            _write_json_atomic(
                out_dir / MARKER,
                {"format": MARKER_FORMAT, "about": "written by image2sim batch; re-running batch here resumes it"},
            )
        (out_dir / RESULTS_DIR).mkdir(exist_ok=True)
        (out_dir / SCENES_DIR).mkdir(exist_ok=True)
    except OSError as exc:
        raise GrounderError(f"cannot create output folder {out_dir} ({exc}); choose another folder (-o)") from exc


_TABLE_COLUMNS = (
    "id",
    "status",
    "scene",
    "trajectories",
    "seconds",
    "train_position_pct_before",
    "train_position_pct_after",
    "validation_position_pct_before",
    "validation_position_pct_after",
    "validation_rotation_deg_before",
    "validation_rotation_deg_after",
    "parameters",
    "error",
)


def _row(job: Job, record: dict[str, Any] | None) -> dict[str, Any]:
    row: dict[str, Any] = {c: "" for c in _TABLE_COLUMNS}
    row.update(id=job.id, scene=str(job.scene), trajectories=str(job.trajectories))
    if record is None:
        row["status"] = "pending"
        return row
    row["status"] = record.get("status", "")
    row["seconds"] = round(float(record.get("seconds", 0.0)), 2)
    row["error"] = record.get("error") or ""
    errors = record.get("errors") or {}
    for when in ("before", "after"):
        for split in ("train", "validation"):
            if split in errors.get(when, {}):
                row[f"{split}_position_pct_{when}"] = round(errors[when][split]["position_pct"], 3)
                if split == "validation":
                    row[f"validation_rotation_deg_{when}"] = round(errors[when][split]["rotation_deg"], 3)
    if record.get("parameters"):
        row["parameters"] = json.dumps({k: round(v, 6) for k, v in record["parameters"].items()})
    return row


def write_table(
    out_dir: Path, jobs: Sequence[Job], inputs: Mapping[str, Mapping[str, Any]] | None = None
) -> list[dict[str, Any]]:
    """Rewrites ``results.csv`` and ``results.json`` from the per-job records; returns the rows.

    Args:
        out_dir: The batch output.
        jobs: The jobs of the file.
        inputs: Each job's inputs by id (:func:`job_inputs`); None: fingerprinted now. A job whose record was
            made from other inputs reads ``pending``: that record is not its result.
    """
    out_dir = Path(out_dir)
    if inputs is None:
        memo: dict[tuple[object, ...], str] = {}
        inputs = {job.id: job_inputs(job, memo=memo) for job in jobs}
    rows = [_row(job, current_result(out_dir, job, inputs[job.id])) for job in jobs]
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(_TABLE_COLUMNS))
    writer.writeheader()
    writer.writerows(rows)
    write_text_atomic(out_dir / "results.csv", buf.getvalue())
    _write_json_atomic(out_dir / "results.json", rows)
    return rows


def read_table(out_dir: Path) -> list[dict[str, Any]] | None:
    """The rows of ``results.json`` (:func:`write_table`), or None when there is none or it cannot be read."""
    try:
        rows = json.loads((Path(out_dir) / "results.json").read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError):
        return None
    return rows if isinstance(rows, list) and all(isinstance(r, dict) for r in rows) else None
