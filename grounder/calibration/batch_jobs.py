"""The jobs file of a batch calibration (its format: the `grounder.calibration.batch` module docstring): `Job`,
reading and checking the file (`load_jobs`), a job's settings as `CalibrateOptions` (`options_from_settings`), and
the check that the jobs' scenes and trajectory folders exist (`check_job_paths`).
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

from grounder.errors import GrounderError, shown

_ID_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")
_JOB_KEYS = {"id", "scene", "trajectories", "format", "settings"}
_TOP_KEYS = {"defaults", "jobs", "matrix"}
_MATRIX_KEYS = {"scenes", "trajectories", "settings"}


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
    from grounder.calibration.options import CalibrateOptions

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
    from grounder.calibration.options import CalibrateOptions

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
    """Reads and validates a jobs file (`grounder.calibration.batch` module docstring); relative paths are resolved
    against its folder.

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
