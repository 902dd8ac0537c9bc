"""The project's trajectory format: a directory of ``.npz`` files, one recorded trajectory each.

Each file holds

- ``time``: (T,) seconds, strictly increasing (it need not start at 0);
- ``qpos``: (T, nq) and ``qvel``: (T, nv) in the scene's MuJoCo joint order and conventions;
- ``ctrl`` (optional): (T, nu), the control held from ``time[t]`` to ``time[t + 1]``.

MuJoCo conventions, stated once here: a free joint's qpos is the world position (3) then the orientation
quaternion w-first (4); its qvel is the world-frame linear velocity (3) then the body-frame angular
velocity (3). A ball joint's qpos is a w-first quaternion and its qvel a body-frame angular velocity.
The sample rate may be coarser than the model timestep; whoever replays a trajectory interpolates or
sub-steps. Extra keys in a file are ignored. Files are read with ``allow_pickle=False``: they are
untrusted input, and an object array in a required key is refused, never unpickled.
"""

from __future__ import annotations

import math
import os
import re
import zipfile
import zlib
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from grounder.errors import TrajectoryError

_REQUIRED_KEYS = ("time", "qpos", "qvel")
_OPTIONAL_KEYS = ("ctrl",)
_SUFFIX = ".npz"
_MAX_ARRAY_BYTES = 1 << 30  # per array: hours of a many-body recording; a bigger claim is a bomb or a bad header
# Integers are accepted (and converted to float64); bool, complex, strings, objects and records are not.
_NUMERIC_KINDS = "iuf"
QUAT_NORM_TOL = 1e-3
"""Largest accepted ``| |quat| - 1 |`` for free- and ball-joint quaternions in a trajectory."""
MAX_STATE_VALUE = 1e10
"""Largest |time|, |qpos|, |qvel| or |ctrl| a trajectory may hold: MuJoCo's ``mjMAXVAL``, beyond which it stops a
simulation as unstable at its first step."""


def _checked_arrays(
    label: str,
    time_s: object,
    qpos: object,
    qvel: object,
    ctrl: object | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """Validates the arrays of one trajectory and returns read-only float64 copies.

    Args:
        label: What to call the trajectory in error messages (a file path or a name).
        time_s: (T,) seconds, strictly increasing, T >= 2.
        qpos: (T, nq) generalised positions.
        qvel: (T, nv) generalised velocities.
        ctrl: (T, nu) controls, or None.

    Returns:
        ``(time_s, qpos, qvel, ctrl)`` as read-only float64 arrays (``ctrl`` stays None if it was None).

    Raises:
        TrajectoryError: if a dtype, shape, value or the time ordering is invalid.
    """
    file_keys = {"time_s": "time", "qpos": "qpos", "qvel": "qvel", "ctrl": "ctrl"}
    raw = {"time_s": time_s, "qpos": qpos, "qvel": qvel, "ctrl": ctrl}
    out: dict[str, np.ndarray] = {}
    for field, value in raw.items():
        if value is None:
            if field == "ctrl":
                continue
            raise TrajectoryError(f"{label}: '{file_keys[field]}' is required but is None; pass an array")
        key = file_keys[field]
        arr = np.asarray(value)
        if arr.dtype.kind not in _NUMERIC_KINDS:
            raise TrajectoryError(
                f"{label}: '{key}' must hold real numbers (int or float), but has dtype {arr.dtype}; "
                f"store it as float64"
            )
        want_ndim = 1 if field == "time_s" else 2
        if arr.ndim != want_ndim:
            want = {"time": "(T,)", "qpos": "(T, nq)", "qvel": "(T, nv)", "ctrl": "(T, nu)"}[key]
            raise TrajectoryError(
                f"{label}: '{key}' must have shape {want}, but has shape {arr.shape}; store one row per time sample"
            )
        out[field] = np.array(arr, dtype=np.float64)  # a copy, so freezing it cannot affect the caller

    num_steps = out["time_s"].shape[0]
    for field, arr in out.items():
        if arr.shape[0] != num_steps:
            raise TrajectoryError(
                f"{label}: '{file_keys[field]}' has {arr.shape[0]} rows but 'time' has {num_steps}; "
                f"every array needs one row per time sample"
            )
    if num_steps < 2:
        raise TrajectoryError(
            f"{label}: a trajectory needs at least 2 time samples, but has {num_steps}; "
            f"record a longer trajectory or drop this file"
        )
    for field, arr in out.items():
        finite = np.isfinite(arr)
        if not finite.all():
            bad = np.argwhere(~finite)[0]
            row = int(bad[0])
            where = f"{file_keys[field]}[{row}]" if arr.ndim == 1 else f"{file_keys[field]}[{row}, {bad[1]}]"
            raise TrajectoryError(
                f"{label}: '{file_keys[field]}' must be finite, but {where}={arr[tuple(bad)]} (row {row}); "
                f"fill or drop the bad samples"
            )
        beyond = np.abs(arr) > MAX_STATE_VALUE  # times too: a step count from 1e300 s does not fit an integer
        if beyond.any():
            bad = np.argwhere(beyond)[0]
            where = ", ".join(str(int(i)) for i in bad)
            raise TrajectoryError(
                f"{label}: '{file_keys[field]}[{where}]' is {arr[tuple(bad)]:.3g}, beyond the "
                f"{MAX_STATE_VALUE:g} MuJoCo can simulate; fix or drop the bad samples"
            )
    time_arr = out["time_s"]
    steps = np.diff(time_arr)
    if not (steps > 0).all():
        i = int(np.argmax(steps <= 0)) + 1
        raise TrajectoryError(
            f"{label}: 'time' must be strictly increasing, but time[{i}]={time_arr[i]:.6g} <= "
            f"time[{i - 1}]={time_arr[i - 1]:.6g}; re-sample or sort the trajectory"
        )
    for arr in out.values():
        arr.flags.writeable = False
    return out["time_s"], out["qpos"], out["qvel"], out.get("ctrl")


def _label(traj: Trajectory) -> str:
    return f"trajectory '{traj.name}'" if traj.name else "trajectory"


@dataclass(frozen=True, kw_only=True, eq=False, repr=False)
class Trajectory:
    """One recorded trajectory of a scene, in the model's joint order (see the module docstring).

    Arrays are converted to float64, copied and made read-only on construction. ``eq`` is identity, as
    element-wise comparison of arrays has no single truth value; compare the arrays themselves instead.

    Attributes:
        time_s: (T,) float64, seconds, strictly increasing, T >= 2.
        qpos: (T, nq) float64, MuJoCo generalised positions (free joint: world position in metres, then
            quaternion w-first).
        qvel: (T, nv) float64, MuJoCo generalised velocities (free joint: world linear velocity in m/s,
            then body-frame angular velocity in rad/s).
        ctrl: (T, nu) float64, the control held from ``time_s[t]`` to ``time_s[t + 1]``, or None if the
            trajectory was recorded without controls.
        name: Identifier, the file stem when loaded; used as the file name when saved.

    Raises:
        TrajectoryError: if an array has a non-numeric dtype or the wrong shape, the arrays disagree on T,
            T < 2, a value is NaN or infinite, or time is not strictly increasing.
    """

    time_s: np.ndarray
    qpos: np.ndarray
    qvel: np.ndarray
    ctrl: np.ndarray | None = None
    name: str = ""

    def __post_init__(self) -> None:
        if not isinstance(self.name, str):
            raise TrajectoryError(f"trajectory name must be a str, but got {type(self.name).__name__}")
        time_s, qpos, qvel, ctrl = _checked_arrays(_label(self), self.time_s, self.qpos, self.qvel, self.ctrl)
        object.__setattr__(self, "time_s", time_s)
        object.__setattr__(self, "qpos", qpos)
        object.__setattr__(self, "qvel", qvel)
        object.__setattr__(self, "ctrl", ctrl)

    def __repr__(self) -> str:
        # The default repr would print every sample.
        return (
            f"Trajectory(name={self.name!r}, num_steps={self.num_steps}, nq={self.nq}, nv={self.nv}, "
            f"nu={self.nu}, duration_s={self.duration_s:.6g})"
        )

    @property
    def num_steps(self) -> int:
        """Number of time samples T."""
        return int(self.time_s.shape[0])

    @property
    def nq(self) -> int:
        """Number of generalised position coordinates (columns of ``qpos``)."""
        return int(self.qpos.shape[1])

    @property
    def nv(self) -> int:
        """Number of degrees of freedom (columns of ``qvel``)."""
        return int(self.qvel.shape[1])

    @property
    def nu(self) -> int:
        """Number of controls (columns of ``ctrl``); 0 when ``ctrl`` is None."""
        return 0 if self.ctrl is None else int(self.ctrl.shape[1])

    @property
    def duration_s(self) -> float:
        """Seconds from the first to the last sample."""
        return float(self.time_s[-1] - self.time_s[0])


def _validate_against_model(traj: Trajectory, model: mujoco.MjModel, label: str) -> None:
    nu_file = "none (no ctrl)" if traj.ctrl is None else str(traj.nu)
    dims_ok = traj.nq == model.nq and traj.nv == model.nv and (traj.ctrl is None or traj.nu == model.nu)
    if not dims_ok:
        raise TrajectoryError(
            f"{label}: does not fit the model, which has nq={model.nq}, nv={model.nv}, nu={model.nu}, "
            f"but the trajectory has nq={traj.nq}, nv={traj.nv}, nu={nu_file}; "
            f"record it with the same scene, or export the scene that produced it"
        )
    for joint_id in range(model.njnt):
        joint_type = model.jnt_type[joint_id]
        if joint_type == mujoco.mjtJoint.mjJNT_FREE:
            start = int(model.jnt_qposadr[joint_id]) + 3  # position (3) comes before the quaternion
        elif joint_type == mujoco.mjtJoint.mjJNT_BALL:
            start = int(model.jnt_qposadr[joint_id])
        else:
            continue
        norm = np.linalg.norm(traj.qpos[:, start : start + 4], axis=1)
        bad = np.abs(norm - 1.0) > QUAT_NORM_TOL
        if bad.any():
            row = int(np.argmax(bad))
            joint_name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, joint_id)
            joint = f"'{joint_name}'" if joint_name else f"#{joint_id} (unnamed)"
            kind = "free" if joint_type == mujoco.mjtJoint.mjJNT_FREE else "ball"
            raise TrajectoryError(
                f"{label}: the quaternion of {kind} joint {joint} (qpos[:, {start}:{start + 4}]) must have "
                f"unit norm within {QUAT_NORM_TOL:g}, but at row {row} its norm is {norm[row]:.6g}; "
                f"normalise the quaternions (w-first) before saving"
            )


def validate_against_model(traj: Trajectory, model: mujoco.MjModel) -> None:
    """Checks that a trajectory fits a MuJoCo model.

    Args:
        traj: The trajectory to check.
        model: The scene it was recorded in.

    Raises:
        TrajectoryError: if ``nq`` or ``nv`` differ from the model's, ``ctrl`` is present with a different
            ``nu``, or a free- or ball-joint quaternion's norm is off 1 by more than ``QUAT_NORM_TOL``.
    """
    _validate_against_model(traj, model, _label(traj))


def load_trajectory(path: str | os.PathLike[str]) -> Trajectory:
    """Reads one trajectory file; its name is the file stem.

    Args:
        path: An ``.npz`` file with keys ``time``, ``qpos``, ``qvel`` and optionally ``ctrl``. Other keys
            are ignored.

    Returns:
        The validated trajectory.

    Raises:
        TrajectoryError: if the file is missing or is not a readable npz archive, a required key is
            missing, an array holds pickled objects or non-numeric data, or the arrays fail the checks of
            :class:`Trajectory`.
    """
    path = Path(path)
    if not path.exists():
        raise TrajectoryError(f"{path}: trajectory file does not exist; check the path")
    if not path.is_file():
        raise TrajectoryError(f"{path}: expected a trajectory .npz file, but found a directory or special file")
    with path.open("rb") as head:
        magic = head.read(6)
    if not (magic.startswith(b"PK") or magic == b"\x93NUMPY"):
        # numpy would try the file as a pickle and refuse it, with a message that suggests allow_pickle
        raise TrajectoryError(
            f"{path}: not an .npz archive (no zip header: {magic!r}); write it with save_trajectory or numpy.savez"
        )
    try:
        archive = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise TrajectoryError(
            f"{path}: not a valid .npz archive ({type(exc).__name__}: {exc}); "
            f"write it with save_trajectory or numpy.savez"
        ) from exc
    if not isinstance(archive, np.lib.npyio.NpzFile):
        raise TrajectoryError(
            f"{path}: expected an .npz archive with keys 'time', 'qpos', 'qvel', but found a single .npy "
            f"array; write it with save_trajectory or numpy.savez"
        )
    arrays: dict[str, np.ndarray] = {}
    with archive:
        missing = [key for key in _REQUIRED_KEYS if key not in archive.files]
        if missing:
            raise TrajectoryError(
                f"{path}: missing required key(s) {missing}; found {sorted(archive.files)}, "
                f"expected 'time', 'qpos', 'qvel' and optionally 'ctrl'"
            )
        for key in (*_REQUIRED_KEYS, *_OPTIONAL_KEYS):
            if key not in archive.files:
                continue
            try:
                _check_member_size(path, archive, key)
                arrays[key] = archive[key]
            except ValueError as exc:
                if "allow_pickle" in str(exc):  # numpy refuses object arrays when allow_pickle=False
                    raise TrajectoryError(
                        f"{path}: '{key}' holds pickled objects, which are refused (nothing was unpickled); "
                        "store plain float64 arrays"
                    ) from exc
                raise TrajectoryError(
                    f"{path}: '{key}' is not a readable array ({' '.join(str(exc).split())}); re-export the trajectory"
                ) from exc
            except (OSError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
                raise TrajectoryError(
                    f"{path}: '{key}' is corrupt ({type(exc).__name__}: {exc}); re-export the trajectory"
                ) from exc
            except (RuntimeError, NotImplementedError) as exc:  # zipfile: an encrypted member, an unknown compression
                raise TrajectoryError(
                    f"{path}: '{key}' cannot be read ({' '.join(str(exc).split())}); write it unencrypted with "
                    "numpy.savez or savez_compressed"
                ) from exc
    time_s, qpos, qvel, ctrl = _checked_arrays(
        str(path), arrays["time"], arrays["qpos"], arrays["qvel"], arrays.get("ctrl")
    )
    return Trajectory(time_s=time_s, qpos=qpos, qvel=qvel, ctrl=ctrl, name=path.stem)


def _check_member_size(path: Path, archive: np.lib.npyio.NpzFile, key: str) -> None:
    """Refuses, before numpy allocates anything, an array whose uncompressed size (from the zip directory) is too
    large, or whose header claims more data than the member holds (a zip bomb, or a corrupt header).

    Raises:
        TrajectoryError: the array is too large or its header lies.
        ValueError, OSError, zipfile.BadZipFile, zlib.error: an unreadable header (the caller words them).
    """
    zip_file = archive.zip
    if zip_file is None:
        return
    # The member numpy reads for `archive[key]`: one named `key` itself first, else `key.npy`.
    member = zip_file.NameToInfo.get(key) or zip_file.NameToInfo.get(f"{key}.npy")
    if member is None:
        return
    if member.file_size > _MAX_ARRAY_BYTES:
        raise TrajectoryError(
            f"{path}: '{key}' is {member.file_size / 1e9:.1f} GB uncompressed, more than the "
            f"{_MAX_ARRAY_BYTES / 1e9:.0f} GB a trajectory array may take; split the recording into shorter "
            "trajectories"
        )
    with zip_file.open(member) as stream:
        version = np.lib.format.read_magic(stream)
        read_header = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
        shape, _, dtype = read_header(stream)
    if dtype.hasobject:
        raise ValueError("Object arrays cannot be loaded when allow_pickle=False")
    claimed = math.prod(shape) * dtype.itemsize
    if claimed > member.file_size:
        raise TrajectoryError(
            f"{path}: '{key}' claims shape {tuple(shape)} ({claimed / 1e9:.3g} GB) but holds {member.file_size} bytes; "
            "the file is corrupt, re-export the trajectory"
        )


def _with_suffix(path: Path) -> Path:
    return path if path.suffix == _SUFFIX else path.with_name(path.name + _SUFFIX)


def save_trajectory(traj: Trajectory, path: str | os.PathLike[str]) -> Path:
    """Writes one trajectory atomically: to a temporary file in the same directory, then renamed.

    A failure leaves any existing file at ``path`` untouched and no temporary file behind. The parent
    directory is created if missing.

    Args:
        traj: The trajectory to write.
        path: Destination; ``.npz`` is appended if the name does not already end with it.

    Returns:
        The path written, with the ``.npz`` suffix.
    """
    final = _with_suffix(Path(path))
    final.parent.mkdir(parents=True, exist_ok=True)
    arrays: dict[str, Any] = {"time": traj.time_s, "qpos": traj.qpos, "qvel": traj.qvel}
    if traj.ctrl is not None:
        arrays["ctrl"] = traj.ctrl
    from image2sim_common.outdir import atomic_file  # here: importing `reconstruction` loads pycolmap

    # The temporary name does not end in .npz, so load_trajectories never picks up a half-written file.
    with atomic_file(final) as handle:
        np.savez(handle, allow_pickle=False, **arrays)
    return final


def _natural_key(name: str) -> tuple[tuple[int | str, ...], str]:
    # re.split with a capture group alternates text, number, text, ..., so parts compare type-for-type.
    parts = tuple(int(p) if i % 2 else p.casefold() for i, p in enumerate(re.split(r"(\d+)", name)))
    return parts, name


def _dims(traj: Trajectory) -> str:
    return f"nq={traj.nq}, nv={traj.nv}, nu={'none (no ctrl)' if traj.ctrl is None else traj.nu}"


SAMPLES_SUFFIX = ".samples.npz"  # a fan of sampled simulations (`grounder.sim.rollout_files`), not a trajectory


def load_trajectories(directory: str | os.PathLike[str], model: mujoco.MjModel | None = None) -> list[Trajectory]:
    """Reads every ``*.npz`` trajectory in a directory, in natural name order (``toss_2`` before ``toss_10``).

    Args:
        directory: Folder of trajectory files; other files and sub-folders are ignored, and so are the sample fans
            ``*.samples.npz`` that ``image2sim rollout --samples`` writes beside each median trajectory.
        model: If given, each trajectory is checked with :func:`validate_against_model`.

    Returns:
        The trajectories, sorted naturally by name.

    Raises:
        TrajectoryError: if the directory is missing, is not a directory or holds no ``.npz`` file, if any
            file is invalid, if the files disagree on nq, nv, nu or on whether ``ctrl`` is present, or if
            one does not fit ``model``.
    """
    directory = Path(directory)
    if not directory.exists():
        raise TrajectoryError(f"{directory}: trajectory directory does not exist; check the path")
    if not directory.is_dir():
        raise TrajectoryError(
            f"{directory}: expected a directory of .npz trajectories, but found a file; pass its folder, "
            f"or use load_trajectory for a single file"
        )
    paths = sorted(
        (p for p in directory.iterdir() if p.suffix == _SUFFIX and not p.name.endswith(SAMPLES_SUFFIX) and p.is_file()),
        key=lambda p: _natural_key(p.stem),
    )
    if not paths:
        raise TrajectoryError(
            f"{directory}: contains no .npz trajectory files; record trajectories or point at the right folder"
        )
    trajs: list[Trajectory] = []
    for path in paths:
        traj = load_trajectory(path)
        if trajs and _dims(traj) != _dims(trajs[0]):
            raise TrajectoryError(
                f"{path}: has {_dims(traj)} but {paths[0].name} has {_dims(trajs[0])}; all trajectories in "
                f"one directory must come from the same scene, and either all have ctrl or none has"
            )
        if model is not None:
            _validate_against_model(traj, model, str(path))
        trajs.append(traj)
    return trajs


def _check_names(trajs: Sequence[Trajectory], directory: Path) -> None:
    seen: dict[str, str] = {}
    for index, traj in enumerate(trajs):
        name = traj.name
        unsafe = (
            not name
            or name in (".", "..")
            or "/" in name
            or "\\" in name
            or "\0" in name
            or (os.altsep is not None and os.altsep in name)
        )
        if unsafe:
            raise TrajectoryError(
                f"{directory}: trajectory #{index} has name {name!r}, which is not a safe file name; "
                f"give each trajectory a non-empty name without path separators"
            )
        # Case-insensitive file systems (macOS, Windows) would let one file overwrite another.
        folded = name.casefold()
        if folded in seen:
            raise TrajectoryError(
                f"{directory}: trajectory names must be unique (ignoring case), but {name!r} and "
                f"{seen[folded]!r} collide; rename one of them"
            )
        seen[folded] = name


def save_trajectories(trajs: Iterable[Trajectory], directory: str | os.PathLike[str]) -> Path:
    """Writes each trajectory as ``{name}.npz`` in a directory.

    All names are checked before anything is written. A new directory is filled under a temporary name
    and renamed into place at the end; in an existing directory each file is replaced atomically and
    other files are left alone.

    Args:
        trajs: Trajectories with unique, non-empty names that are safe file names.
        directory: Destination folder, created if missing.

    Returns:
        The directory.

    Raises:
        TrajectoryError: if there are no trajectories, or a name is empty, contains a path separator,
            or repeats another (ignoring case).
    """
    directory = Path(directory)
    trajs = list(trajs)
    if not trajs:
        raise TrajectoryError(f"{directory}: no trajectories to save; pass at least one")
    _check_names(trajs, directory)
    if directory.exists() and not directory.is_dir():
        raise TrajectoryError(f"{directory}: exists and is not a directory; choose another output folder")
    if directory.is_dir():
        for traj in trajs:
            save_trajectory(traj, directory / f"{traj.name}{_SUFFIX}")
        return directory
    from image2sim_common.outdir import staged_output_dir  # here: importing `reconstruction` loads pycolmap

    with staged_output_dir(directory, error=TrajectoryError) as staging:
        for traj in trajs:
            save_trajectory(traj, staging / f"{traj.name}{_SUFFIX}")
    return directory
