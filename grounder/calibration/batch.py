"""Batch calibration jobs (scenes x datasets x settings) on Ray, resumable.

A jobs file (YAML; relative paths are relative to the file, ``~`` is the home folder)::

    defaults:                      # optional: CalibrateOptions fields applied to every job
      generations: 10
      max_train_trajectories: 40
    jobs:                          # explicit jobs
      - id: cube_default           # optional; default: <scene stem>__<dataset name>__<settings name>
        scene: ../samples/cube_toss/cube.xml
        trajectories: cube_npz/    # a trajectory folder (.npz files) ...
        format: dair-pll-cube      # ... or, with format, a folder an importer reads (image2sim import-trajectories)
        settings: {params: [cube.friction.sliding, cube.solref.timeconst]}
    matrix:                        # optional: every scene x every dataset x every named setting
      scenes: [a/scene_dir, b.xml]
      trajectories: [data1/, {path: ../shared/data/cube_toss, format: dair-pll-cube}]
      settings: {fast: {generations: 2}, full: {}}

Output folder (new, empty, or the output of an earlier batch run, which its ``batch.json`` marks)::

    batch.json          the marker, written before any job runs: ``{"format": "image2sim-batch/1", ...}``. A folder
                        that is not empty and has no marker is refused, since a run replaces what it finds there
    results/<id>.json   one per finished job, written atomically (temporary file, then os.replace): the job's
                        status (ok or failed with the error), parameters, errors before/after, seconds, and
                        ``inputs``: sha256 fingerprints of what it read (:func:`job_inputs`)
    scenes/<id>/        the calibrated scene folder of a successful job (written atomically by calibrate)
    results.csv, results.json   the table of all jobs of the file, rewritten after each finished job and on the way
                        out (also after SIGINT or SIGTERM); a record whose inputs are not the job's now reads pending

A job counts as finished when its ``results/<id>.json`` says ``ok`` and its recorded inputs are the job's inputs now:
the same settings (canonical JSON), scene files (the MJCF and every file it names; for a scene folder also its other
top-level files) and trajectory files (names and contents). A re-run (after a crash or Ctrl-C) skips it and runs the
rest; a job whose settings, scene or trajectories changed runs again, with a warning that names what changed, and so
does one whose record has no fingerprint (written by an older image2sim). Failed jobs are run again, and so are jobs
whose record is unreadable or invalid (with a warning). A failing job is recorded and does not stop the others.
SIGINT or SIGTERM stops a Ray run within a second: the jobs still running are cancelled, Ray is shut down, the
table is rewritten from the records, and the signal is then handed to the handler the caller had before. A scene or
trajectory folder that is not there is refused before any job runs (not with ``address``: on a cluster the paths
need only exist on its nodes, and an input not visible here is left out of the comparison of inputs). Jobs
run as Ray tasks (one CPU each) on a local Ray started for the run, or on an existing cluster given by
``address``: the head node's ``host:port`` (its GCS port, 6379 by default), ``auto`` (the cluster ``ray start``
made on this machine) or ``ray://host:10001`` (the Ray client, which needs ``pip install 'ray[client]'``); the
cluster's nodes need image2sim installed and the paths visible.
A cluster that cannot be reached is reported before the output folder is created.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import logging
import os
import re
import shutil
import signal
import socket
import threading
import time
import traceback
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

from grounder.core.html_report import write_text_atomic
from grounder.errors import GrounderError, shown
from image2sim_common.progress import ProgressFn

log = logging.getLogger(__name__)


RESULTS_DIR = "results"
SCENES_DIR = "scenes"
_ID_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")
_JOB_KEYS = {"id", "scene", "trajectories", "format", "settings"}
_TOP_KEYS = {"defaults", "jobs", "matrix"}
_MATRIX_KEYS = {"scenes", "trajectories", "settings"}
MARKER = "batch.json"
MARKER_FORMAT = "image2sim-batch/1"
_WAIT_SLICE_S = 0.5  # how long one ray.wait may block: a SIGINT or SIGTERM is acted on within this
_CANCEL_WAIT_S = 60.0  # at most this long for the workers of cancelled jobs to go (a cluster's may answer slowly)


@dataclass(frozen=True, kw_only=True)
class Job:
    """One calibration job.

    Attributes:
        id: Unique, file-name safe identifier.
        scene: MJCF file or scene folder.
        trajectories: Trajectory folder, or a folder read with the importer ``format``.
        format: Importer name (``dair-pll-cube``) or None for the project's trajectory format.
        settings: `CalibrateOptions` fields (defaults merged in).
    """

    id: str
    scene: Path
    trajectories: Path
    format: str | None = None
    settings: Mapping[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "scene": str(self.scene),
            "trajectories": str(self.trajectories),
            "format": self.format,
            "settings": dict(self.settings),
        }

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> Job:
        return cls(
            id=data["id"],
            scene=Path(data["scene"]),
            trajectories=Path(data["trajectories"]),
            format=data.get("format"),
            settings=dict(data.get("settings") or {}),
        )


def _options_fields() -> set[str]:
    from grounder.calibration.fit import CalibrateOptions

    return {f.name for f in fields(CalibrateOptions)}


def _keys(keys: Iterable[object]) -> str:
    """Keys read from a user's file for an error line: sorted by their text (a file may mix ``1`` and ``a``)."""
    return ", ".join(shown(k) for k in sorted(keys, key=str))


def _check_settings(where: str, settings: object) -> dict[str, Any]:
    if settings is None:
        return {}
    if not isinstance(settings, Mapping):
        raise GrounderError(f"{where}: settings must be a mapping of calibrate options, got {type(settings).__name__}")
    unknown = set(settings) - _options_fields()
    if unknown:
        raise GrounderError(
            f"{where}: unknown setting(s) {_keys(unknown)}; known: {', '.join(sorted(_options_fields()))}"
        )
    return dict(settings)


def options_from_settings(settings: Mapping[str, Any]) -> Any:
    """`CalibrateOptions` from a job's settings (lists become tuples)."""
    from grounder.calibration.fit import CalibrateOptions

    values: dict[str, Any] = {k: tuple(v) if isinstance(v, list) else v for k, v in settings.items()}
    if isinstance(values.get("params"), str):
        values["params"] = tuple(p for p in values["params"].split(",") if p)
    try:
        return CalibrateOptions(**values)
    except (TypeError, ValueError) as exc:  # a value of the wrong type that the checks compare or measure
        raise GrounderError(f"invalid settings {shown(dict(settings), limit=200)}: {exc}") from exc


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", text).strip("_.") or "x"


def _list(where: str, value: object, what: str) -> list[Any]:
    """``value`` as a list; a scalar or a mapping (``jobs: 5``, ``scenes: a.xml``) is refused."""
    if isinstance(value, Sequence) and not isinstance(value, (str, bytes)):
        return list(value)
    raise GrounderError(f"{where} must be a list of {what}, got {type(value).__name__} {shown(value)}")


def _path(where: str, value: object, root: Path) -> Path:
    if not isinstance(value, str) or not value:
        raise GrounderError(f"{where} must be a path (text), got {type(value).__name__} {shown(value)}")
    if "\0" in value:  # no file name can hold one; Path.resolve would raise ValueError
        raise GrounderError(f"{where} contains a NUL character: {shown(value)}; write the path without it")
    try:  # ~ and ~user as a shell would expand them: a YAML file is not passed through one
        return (root / Path(value).expanduser()).resolve()
    except (OSError, RuntimeError) as exc:  # a symbolic link loop (RuntimeError before Python 3.13); unknown ~user
        raise GrounderError(f"{where}: {shown(value)} cannot be resolved ({exc}); fix the path") from exc


def _check_format(where: str, fmt: object) -> str | None:
    """An importer name known to `grounder.core.importers.import_trajectories`, or None (the project's .npz folders)."""
    from grounder.core.importers import IMPORTERS

    if fmt is None or (isinstance(fmt, str) and fmt in IMPORTERS):
        return fmt
    raise GrounderError(
        f"{where}: unknown trajectory format {shown(fmt)}; known formats: {', '.join(sorted(IMPORTERS))} "
        "(leave 'format' out for a folder of .npz trajectories)"
    )


def _dataset(where: str, entry: object, root: Path) -> tuple[Path, str | None]:
    if isinstance(entry, str):
        return _path(f"{where}: trajectories", entry, root), None
    if isinstance(entry, Mapping) and "path" in entry and set(entry) <= {"path", "format"}:
        return _path(f"{where}: trajectories.path", entry["path"], root), _check_format(where, entry.get("format"))
    raise GrounderError(f"{where}: a dataset is a path or {{path: ..., format: ...}}, got {shown(entry)}")


class _DuplicateKey(Exception):
    """A mapping of the jobs file has the same key twice (``line``: 1-based; ``first_line``: the first one)."""

    def __init__(self, key: object, line: int, first_line: int) -> None:
        super().__init__(key, line, first_line)
        self.key, self.line, self.first_line = key, line, first_line


def _yaml_loader() -> type:
    """A `yaml.SafeLoader` that refuses a key repeated in one mapping (PyYAML keeps the last one silently).

    Checked on the composed nodes, before merge keys (``<<: *base``) are expanded, so a key that overrides a merged
    one is not a repetition.
    """
    import yaml

    class JobsLoader(yaml.SafeLoader):
        def compose_mapping_node(self, anchor: Any) -> Any:
            node = super().compose_mapping_node(anchor)
            first: dict[Any, int] = {}
            for key_node, _ in node.value:
                if not isinstance(key_node, yaml.ScalarNode) or key_node.tag == "tag:yaml.org,2002:merge":
                    continue  # a list or mapping as key: SafeLoader refuses it (unhashable)
                key = self.construct_object(key_node)
                line = key_node.start_mark.line + 1
                if key in first:
                    raise _DuplicateKey(key, line, first[key])
                first[key] = line
            return node

    return JobsLoader


def load_jobs(path: Path) -> list[Job]:
    """Reads and validates a jobs file (module docstring); relative paths are resolved against its folder.

    Raises:
        GrounderError: the file is missing or not YAML text (or nested too deeply), repeats a key in a mapping, has
            unknown keys, fields of the wrong type, unknown settings or trajectory formats, no job, or repeated ids;
            or a job's settings (defaults merged in) are refused by `CalibrateOptions`.
    """
    import yaml

    path = Path(path)
    if path.is_dir():
        raise GrounderError(f"{path} is a folder; pass the jobs file (YAML) itself, e.g. {path / 'jobs.yaml'}")
    if not path.is_file():
        raise GrounderError(f"{path}: jobs file does not exist; pass the path of a jobs file (YAML)")
    try:
        data = yaml.load(path.read_bytes().decode("utf-8"), Loader=_yaml_loader())  # a yaml.SafeLoader
    except UnicodeDecodeError as exc:
        raise GrounderError(f"{path}: not a YAML text file (not UTF-8: {exc}); pass a jobs file (YAML)") from exc
    except _DuplicateKey as exc:
        raise GrounderError(
            f"{path}: line {exc.line}: key {shown(exc.key)} appears twice in one mapping (first on line "
            f"{exc.first_line}); keep one of them"
        ) from exc
    except RecursionError as exc:
        raise GrounderError(f"{path}: not a readable YAML file (nested too deeply); pass a jobs file (YAML)") from exc
    except (OSError, yaml.YAMLError) as exc:
        raise GrounderError(f"{path}: not a readable YAML file ({exc})".replace("\n", " ")) from exc
    if not isinstance(data, Mapping):
        raise GrounderError(f"{path}: expected a mapping with 'jobs' and/or 'matrix', got {type(data).__name__}")
    unknown = set(data) - _TOP_KEYS
    if unknown:
        raise GrounderError(f"{path}: unknown key(s) {_keys(unknown)}; expected {', '.join(sorted(_TOP_KEYS))}")
    root = path.parent.resolve()
    defaults = _check_settings(f"{path}: defaults", data.get("defaults"))
    jobs: list[Job] = []
    raw_jobs = data.get("jobs")
    for i, entry in enumerate(_list(f"{path}: 'jobs'", raw_jobs, "jobs") if raw_jobs is not None else []):
        where = f"{path}: jobs[{i}]"
        if not isinstance(entry, Mapping) or not {"scene", "trajectories"} <= set(entry):
            raise GrounderError(f"{where}: a job needs 'scene' and 'trajectories'")
        if set(entry) - _JOB_KEYS:
            raise GrounderError(
                f"{where}: unknown key(s) {_keys(set(entry) - _JOB_KEYS)}; expected {', '.join(sorted(_JOB_KEYS))}"
            )
        scene = _path(f"{where}: scene", entry["scene"], root)
        trajectories, fmt = _dataset(where, entry["trajectories"], root)
        fmt = _check_format(where, entry.get("format", fmt))
        settings = {**defaults, **_check_settings(where, entry.get("settings"))}
        job_id = str(entry.get("id") or f"{_slug(scene.stem)}__{_slug(trajectories.name)}__{i}")
        jobs.append(Job(id=job_id, scene=scene, trajectories=trajectories, format=fmt, settings=settings))
    matrix = data.get("matrix")
    if matrix is not None:
        if not isinstance(matrix, Mapping) or not {"scenes", "trajectories"} <= set(matrix):
            raise GrounderError(f"{path}: matrix needs 'scenes' and 'trajectories' lists (and optional 'settings')")
        if set(matrix) - _MATRIX_KEYS:
            raise GrounderError(
                f"{path}: matrix: unknown key(s) {_keys(set(matrix) - _MATRIX_KEYS)}; "
                f"expected {', '.join(sorted(_MATRIX_KEYS))}"
            )
        scenes = [
            _path(f"{path}: matrix.scenes[{k}]", s, root)
            for k, s in enumerate(_list(f"{path}: matrix.scenes", matrix["scenes"], "scene paths"))
        ]
        datasets = [
            _dataset(f"{path}: matrix.trajectories[{k}]", d, root)
            for k, d in enumerate(_list(f"{path}: matrix.trajectories", matrix["trajectories"], "datasets"))
        ]
        raw_settings = matrix.get("settings") or {"default": {}}
        named: dict[str, Any] = {}
        if isinstance(raw_settings, Sequence) and not isinstance(raw_settings, (str, bytes)):
            for k, s in enumerate(raw_settings):
                if not isinstance(s, Mapping):
                    raise GrounderError(
                        f"{path}: matrix.settings[{k}] must be a mapping of calibrate options (and an optional "
                        f"'name'), got {type(s).__name__} {shown(s)}"
                    )
                name = str(s.get("name", f"s{k}"))
                if name in named:
                    raise GrounderError(
                        f"{path}: matrix.settings name {shown(name)} appears twice; give distinct names"
                    )
                named[name] = {kk: v for kk, v in s.items() if kk != "name"}
        elif isinstance(raw_settings, Mapping):
            named = {str(k): v for k, v in raw_settings.items()}
        else:
            raise GrounderError(
                f"{path}: matrix.settings must be a mapping name -> settings or a list of settings, "
                f"got {type(raw_settings).__name__} {shown(raw_settings)}"
            )
        for scene in scenes:
            for trajectories, fmt in datasets:
                for sname, sval in named.items():
                    settings = {**defaults, **_check_settings(f"{path}: matrix.settings.{sname}", sval)}
                    scene_label = _slug(scene.stem if scene.suffix else scene.name)
                    job_id = f"{scene_label}__{_slug(trajectories.name)}__{_slug(sname)}"
                    jobs.append(Job(id=job_id, scene=scene, trajectories=trajectories, format=fmt, settings=settings))
    if not jobs:
        raise GrounderError(f"{path}: holds no job; add a 'jobs' list or a 'matrix'")
    seen: set[str] = set()
    for job in jobs:
        if not _ID_RE.match(job.id):
            raise GrounderError(f"{path}: job id {shown(job.id)} is not a safe file name; use letters, digits, _ . -")
        if job.id in seen:
            raise GrounderError(f"{path}: job id {shown(job.id)} appears twice; give the jobs distinct ids")
        seen.add(job.id)
        try:  # fail before any work starts; the merged settings (defaults, then the job's or the matrix's)
            options_from_settings(job.settings)
        except (GrounderError, TypeError, ValueError) as exc:
            raise GrounderError(f"{path}: job {job.id}: {exc}") from exc
    return jobs


def check_job_paths(jobs: Sequence[Job]) -> None:
    """Refuses jobs whose scene or trajectory folder is missing, before Ray starts or the output folder exists.

    Raises:
        GrounderError: naming the first missing path, its job, and how many paths are missing in all.
    """
    missing = [
        (job.id, what, path)
        for job in jobs
        for what, path, ok in (
            ("scene", job.scene, job.scene.exists()),
            ("trajectories", job.trajectories, job.trajectories.is_dir()),
        )
        if not ok
    ]
    if missing:
        job_id, what, path = missing[0]
        more = f" (and {len(missing) - 1} more missing path(s))" if len(missing) > 1 else ""
        kind = "folder" if what == "trajectories" else "scene"
        raise GrounderError(
            f"job {job_id}: {what} {path} is not an existing {kind}{more}; fix the path in the jobs file "
            "(relative paths are relative to the jobs file)"
        )


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
    (`grounder.sim.rollout.scene_files`: meshes, textures, included MJCF), and for a scene folder also its other
    top-level files (``scene.json``, which embedding mode reads). MISSING when ``scene`` is not there."""
    from grounder.sim.rollout import SCENE_XML, scene_files

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


def run_job(job_json: Mapping[str, Any], out_dir: str) -> dict[str, Any]:
    """Runs one job and writes its result record atomically; never raises (a failure is recorded).

    Runs inside a Ray worker (or inline). Returns the record.
    """
    job = Job.from_json(job_json)
    out = Path(out_dir)
    scene_out = out / SCENES_DIR / job.id
    tick = time.time()
    record: dict[str, Any] = {"id": job.id, "job": job.to_json(), "started_unix": tick, "pid": os.getpid()}
    try:
        record["inputs"] = job_inputs(job)  # before reading them: what this run read, barring an edit meanwhile
        from grounder.calibration.fit import calibrate
        from grounder.core.importers import import_trajectories
        from grounder.core.trajectory import load_trajectories

        options = options_from_settings({"nthread": 1, **job.settings})
        if job.format:
            trajs = import_trajectories(job.format, job.trajectories)
        else:
            trajs = load_trajectories(job.trajectories)
        if scene_out.exists():
            shutil.rmtree(scene_out)  # a scene written before a crash whose result record was not
        result = calibrate(job.scene, trajs, options=options, out=scene_out)
        summary = result.to_json()
        record.update(
            status="ok",
            error=None,
            parameters={p.name: p.value for p in result.parameters},
            intervals={p.name: [p.interval_low, p.interval_high] for p in result.parameters},
            errors={
                when: {
                    split: {
                        "position_pct": float(s.position_pct.mean()),
                        "rotation_deg": float(s.rotation_deg.mean()),
                        "count": len(s.names),
                    }
                    for split, s in side.items()
                }
                for when, side in (("before", result.before), ("after", result.after))
            },
            steps_per_second=summary["steps_per_second"],
            scene_out=str(scene_out),
        )
    except GrounderError as exc:
        record.update(status="failed", error=str(exc))
    except Exception as exc:  # a job's crash must not stop the batch: record it with its traceback
        record.update(status="failed", error=f"{type(exc).__name__}: {exc}", traceback=traceback.format_exc())
    record["seconds"] = time.time() - tick
    _write_json_atomic(result_path(out, job.id), record)
    return record


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


@dataclass(frozen=True, kw_only=True)
class BatchSummary:
    """What a batch run did.

    Attributes:
        total: Jobs in the file.
        skipped: Jobs already finished before this run.
        ran: Jobs run now.
        failed: Ids of jobs that failed (now or before, and still not ok).
        rows: The results table.
        seconds: Wall time.
    """

    total: int
    skipped: tuple[str, ...]
    ran: tuple[str, ...]
    failed: tuple[str, ...]
    rows: tuple[dict[str, Any], ...]
    seconds: float


def ray_init_kwargs(address: str | None, num_cpus: int | None) -> dict[str, Any]:
    """Arguments of ``ray.init``: connect to ``address`` when given, else start a small local Ray."""
    if address:
        return {"address": address, "log_to_driver": False}
    return {
        "num_cpus": num_cpus or max(1, (os.cpu_count() or 2) - 1),
        "include_dashboard": False,
        "log_to_driver": False,
        "configure_logging": False,
    }


_HOST_PORT = re.compile(r"^(?:ray://)?(?P<host>\[[0-9a-fA-F:]+\]|[A-Za-z0-9_.-]+):(?P<port>[0-9]{1,5})$")


def check_ray_address(address: str, *, timeout_s: float = 10.0) -> None:
    """Refuses a cluster address that cannot work, before Ray is asked (Ray itself may hang or print a traceback).

    Args:
        address: ``auto``, ``host:port`` or ``ray://host:port``.
        timeout_s: How long to wait for the TCP connection to ``host:port``.

    Raises:
        GrounderError: Not one of those forms; ``ray://`` without the Ray client installed; nothing listening.
    """
    if address == "auto":
        return
    match = _HOST_PORT.match(address)
    if match is None or not 0 < int(match["port"]) < 65536:
        raise GrounderError(
            f"--address {address!r} is not a Ray cluster address; give the head node's host:port (e.g. head:6379), "
            "auto, or leave --address out for a local Ray"
        )
    if address.startswith("ray://"):
        import importlib.util

        if importlib.util.find_spec("grpc") is None:
            raise GrounderError(
                f"--address {address}: ray:// addresses need the Ray client, which is not installed; run "
                "`.venv/bin/pip install 'ray[client]'`, or give the head node's GCS address (host:6379)"
            )
    host, port = match["host"].strip("[]"), int(match["port"])
    try:
        socket.create_connection((host, port), timeout=timeout_s).close()
    except OSError as exc:
        raise GrounderError(
            f"--address {address}: nothing answers at {host}:{port} ({exc.strerror or exc}); check that the Ray head "
            "node runs (`ray start --head`) and the host and port, or leave --address out for a local Ray"
        ) from exc


def connect_ray(address: str | None, num_cpus: int | None) -> None:
    """``ray.init`` for a batch run (:func:`ray_init_kwargs`); a cluster that cannot be joined is a user error."""
    import ray

    if address:
        check_ray_address(address)
    try:
        ray.init(**ray_init_kwargs(address, num_cpus))
    except (ConnectionError, ValueError, RuntimeError, TimeoutError) as exc:
        where = f"the Ray cluster at {address}" if address else "a local Ray"
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise GrounderError(
            f"cannot start or join {where} ({first}); check --address, or run with --inline to go without Ray"
        ) from exc


def run_batch(
    jobs: Sequence[Job],
    out_dir: Path,
    *,
    address: str | None = None,
    num_cpus: int | None = None,
    inline: bool = False,
    progress: ProgressFn | None = None,
) -> BatchSummary:
    """Runs the jobs not yet finished in ``out_dir`` on Ray (or ``inline``, one after another, without Ray).

    A job is finished when its record says ok and was made from the job's inputs as they are now (module docstring);
    a finished job whose inputs changed is run again, with a warning naming what changed.

    SIGINT and SIGTERM (on the main thread): inline, the handlers in place raise as usual, in the job that runs. On
    Ray they are only noted while the jobs run (`_StopSignals`), and the run stops at once: the jobs not yet done are
    cancelled and waited for, Ray is shut down, the table is rewritten from the records, and then the signal is
    handed to the handler the caller had before ``ray.init`` replaced SIGTERM's (the CLI's raises; Python's default
    for SIGINT raises KeyboardInterrupt; SIG_DFL ends the process as the signal would have).

    Args:
        jobs: From :func:`load_jobs`.
        out_dir: Output folder (module docstring): created if missing; an earlier batch output is reused to resume.
        address: A Ray cluster address; None starts a local Ray for this run.
        num_cpus: CPUs of the local Ray (one job per CPU); ignored with ``address``.
        inline: Run in this process without Ray (debugging, tiny batches).
        progress: ``progress(stage, done, total)``.

    Returns:
        The summary; failed jobs are listed, not raised.

    Raises:
        GrounderError: ``out_dir`` is refused by :func:`check_batch_output`, a pending job's scene or trajectory
            folder is missing (checked without ``address``), or Ray cannot be started or the cluster at ``address``
            joined (all before the output folder is created or any job runs).
    """
    tick = time.time()
    out_dir = Path(out_dir)
    check_batch_output(out_dir)
    memo: dict[tuple[object, ...], str] = {}
    inputs = {job.id: job_inputs(job, seen_here=address is None, memo=memo) for job in jobs}
    skipped: list[str] = []
    for job in jobs:
        record, problem = _load_result(out_dir, job.id)
        if problem:  # e.g. edited by hand or truncated by a full disk: the job's result cannot be trusted
            log.warning("%s: %s; running the job again", result_path(out_dir, job.id), problem)
        elif record is not None and record.get("status") == "ok":
            why = stale_reason(record, inputs[job.id])
            if why:
                log.warning("job %s: %s, re-running", job.id, why)
            elif (out_dir / SCENES_DIR / job.id).is_dir():
                skipped.append(job.id)
    pending = [j for j in jobs if j.id not in set(skipped)]
    if address is None:  # on a cluster the paths need only exist on its nodes
        check_job_paths(pending)
    ran: list[str] = []
    rows: list[dict[str, Any]] = []
    stop = _StopSignals()
    on_ray = bool(pending) and not inline
    started_here = False
    try:
        if on_ray:
            import ray

            started_here = not ray.is_initialized()
            try:
                if started_here:
                    connect_ray(address, num_cpus)  # before the output exists: a bad address leaves nothing behind
                stop.defer()  # after ray.init, which puts its own SIGTERM handler in place of the caller's
            except SystemExit:  # SIGTERM while ray.init ran: its handler calls sys.exit
                stop.received.append(signal.SIGTERM)
        if not stop.received:
            _prepare_output(out_dir, jobs)
            _run_pending(jobs, pending, skipped, out_dir, inputs, ran, inline=inline, progress=progress, stop=stop)
    finally:
        try:  # a signal meanwhile is still only noted: the table is written whatever comes
            if started_here:
                import ray

                ray.shutdown()
            if _is_marker(out_dir / MARKER):  # true once no worker is left to write a record (also after a signal)
                rows = write_table(out_dir, jobs, inputs)
        finally:
            if on_ray:
                stop.restore()
    stop.hand_over()
    failed = tuple(r["id"] for r in rows if r["status"] == "failed")
    return BatchSummary(
        total=len(jobs),
        skipped=tuple(skipped),
        ran=tuple(ran),
        failed=failed,
        rows=tuple(rows),
        seconds=time.time() - tick,
    )


class _StopSignals:
    """SIGINT and SIGTERM noted, not raised, while Ray runs the jobs; then handed to the handlers they replaced.

    Why not let a handler raise: ``ray.init`` replaces the SIGTERM handler with its own, and while ``ray.wait``
    blocks in Ray's core worker a signal meets Ray's C++ handler (which prints a stack trace and exits 1, the exit
    code of a failed job) or, for an exception of our own, is held until the task ends and then surfaces as a
    SystemError. A handler that only notes the signal works whatever Ray does: the loop waits in short slices and
    stops at the next one, and the exception is raised once Ray is shut down and the table is true.

    Only on the main thread (Python runs handlers there), and not for a signal the caller ignores (SIG_IGN).
    """

    _SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self) -> None:
        self.received: list[int] = []
        on_main = threading.current_thread() is threading.main_thread()
        self._before: dict[int, Any] = {s: signal.getsignal(s) for s in self._SIGNALS} if on_main else {}

    def __bool__(self) -> bool:
        return bool(self.received)

    def defer(self) -> None:
        for signum, before in self._before.items():
            if before is not signal.SIG_IGN:
                signal.signal(signum, lambda s, _frame: self.received.append(s))

    def restore(self) -> None:
        """Puts the caller's handlers back (Ray's SIGTERM handler stays after ``ray.shutdown`` otherwise)."""
        for signum, before in self._before.items():
            signal.signal(signum, before if before is not None else signal.SIG_DFL)  # None: not set from Python

    def hand_over(self) -> None:
        """Delivers the first signal received to the caller's handler, which raises (or, SIG_DFL, ends the process)."""
        if not self.received:
            return
        signum = self.received[0]
        before = self._before.get(signum, signal.SIG_DFL)
        if callable(before):
            before(signum, None)
        elif before is not signal.SIG_IGN:
            signal.raise_signal(signum)


def _run_pending(
    jobs: Sequence[Job],
    pending: Sequence[Job],
    skipped: Sequence[str],
    out_dir: Path,
    inputs: Mapping[str, Mapping[str, Any]],
    ran: list[str],
    *,
    inline: bool,
    progress: ProgressFn | None,
    stop: _StopSignals,
) -> None:
    """:func:`run_batch` once Ray (if used) is up and the output exists: runs ``pending`` (appended to ``ran`` as
    they end) and rewrites the table after each; on a signal (``stop``), cancels the jobs not done and waits for them.
    """
    report: ProgressFn = progress or (lambda _s, _d, _t: None)
    # Leftovers of a run that was killed while writing: temporary files and folders (never results).
    for leftover in [*(out_dir / RESULTS_DIR).glob(".*.tmp"), *(out_dir / SCENES_DIR).glob(".*.tmp")]:
        if leftover.is_dir():
            shutil.rmtree(leftover, ignore_errors=True)
        else:
            leftover.unlink(missing_ok=True)
    total = len(jobs)
    done = len(skipped)
    stage = "batch jobs"
    report(stage, done, total)
    if skipped:
        log.info("skipping %d finished job(s)", len(skipped))
    write_table(out_dir, jobs, inputs)
    if pending and inline:
        for job in pending:
            record = run_job(job.to_json(), str(out_dir))
            ran.append(job.id)
            done += 1
            _log_record(record)
            write_table(out_dir, jobs, inputs)
            report(stage, done, total)
    elif pending:
        import ray

        remote = ray.remote(num_cpus=1, max_retries=0)(run_job)
        refs = {remote.remote(job.to_json(), str(out_dir)): job for job in pending}
        waiting = list(refs)
        while waiting and not stop:
            ready, waiting = ray.wait(waiting, num_returns=1, timeout=_WAIT_SLICE_S)
            for ref in ready:
                job = refs[ref]
                try:
                    record = ray.get(ref)
                except Exception as exc:  # the worker died (killed, out of memory): record it here
                    record = {
                        "id": job.id,
                        "job": job.to_json(),
                        "inputs": dict(inputs[job.id]),
                        "status": "failed",
                        "error": f"worker failed: {type(exc).__name__}: {exc}".splitlines()[0],
                    }
                    _write_json_atomic(result_path(out_dir, job.id), record)
                ran.append(job.id)
                done += 1
                _log_record(record)
                write_table(out_dir, jobs, inputs)
                report(stage, done, total)
        if waiting:  # stopped: no job may write its record after the table is rewritten on the way out
            for ref in waiting:
                ray.cancel(ref, force=True)  # a running job's worker is killed; a queued one never starts
            ray.wait(waiting, num_returns=len(waiting), timeout=_CANCEL_WAIT_S)
            log.info("stopped: %d job(s) cancelled", len(waiting))


def _log_record(record: Mapping[str, Any]) -> None:
    if record.get("status") == "ok":
        log.info("job %s finished in %.1f s", record.get("id"), float(record.get("seconds", 0.0)))
    else:
        log.warning("job %s failed: %s", record.get("id"), record.get("error"))
