"""Importers that convert other projects' recorded motion into the project's trajectory format.

Only one format so far, ``dair-pll-cube``: the real cube tosses of Acosta, Yang & Posa (RA-L 2022) as shipped in
``../shared/data/cube_toss`` (see its README). Each ``tosses/N.pt`` is a ``torch.save``d float64 tensor (T, 13),
one row per camera frame at 148 Hz:

=========  ==================================================  ==========================
columns    meaning                                             frame, unit
=========  ==================================================  ==========================
0-3        orientation quaternion, w first                     body -> world
4-6        position of the cube centre                         world, m
7-9        angular velocity                                    body frame, rad/s
10-12      linear velocity                                     world, m/s
=========  ==================================================  ==========================

which maps directly onto a MuJoCo free joint: ``qpos = [pos, quat_wxyz]``, ``qvel = [v_world, omega_body]``.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path

import numpy as np

from grounder.core.trajectory import Trajectory
from grounder.errors import GrounderError

DAIR_PLL_CUBE_RATE_HZ = 148.0
"""Camera frame rate of the cube tosses (dt = 1/148 s; the 0.0068 s sometimes quoted is a rounded value)."""

_NUM_COLUMNS = 13
_QUAT_RENORM_TOL = 1e-3


def _tosses_dir(src_dir: Path) -> Path:
    src_dir = Path(src_dir)
    if not src_dir.exists():
        raise GrounderError(f"{src_dir}: does not exist; pass the cube_toss folder (with tosses/) or tosses/ itself")
    if not src_dir.is_dir():
        raise GrounderError(f"{src_dir}: is not a directory; pass the cube_toss folder or its tosses/ folder")
    if (src_dir / "tosses").is_dir():
        return src_dir / "tosses"
    return src_dir


def load_dair_pll_cube(src_dir: Path) -> list[Trajectory]:
    """Reads the dair-pll cube tosses as trajectories of a single free-joint cube (nq = 7, nv = 6).

    Args:
        src_dir: The dataset folder holding ``tosses/N.pt``, or the ``tosses`` folder itself.

    Returns:
        One trajectory per toss, sorted by toss number; ``name`` is the toss number (``"17"``), ``time_s`` is
        ``k / 148`` for frame k, ``qpos`` is ``[pos_m, quat_wxyz]`` (quaternion renormalised), ``qvel`` is
        ``[v_world_m_s, omega_body_rad_s]``, ``ctrl`` is None.

    Raises:
        GrounderError: the folder is missing, holds no ``N.pt`` file, or a file is not a (T, 13) tensor of
            finite numbers with unit quaternions.
    """
    import torch

    from grounder.core.torch_files import quiet_pickle_protocol_warning, tensor_problem

    folder = _tosses_dir(src_dir)
    files = [p for p in folder.iterdir() if p.is_file() and re.fullmatch(r"\d+\.pt", p.name)]
    if not files:
        raise GrounderError(
            f"{folder}: holds no toss files named N.pt; pass the cube_toss folder (with tosses/) or tosses/ itself"
        )
    files.sort(key=lambda p: int(p.stem))
    out: list[Trajectory] = []
    for path in files:
        try:
            with quiet_pickle_protocol_warning():  # torch's two-line warning before it fails on a plain pickle
                tensor = torch.load(path, weights_only=True, map_location="cpu")
        except Exception as exc:  # torch raises many types for corrupt or unsafe files
            # Not torch's own text: it runs over several lines and suggests weights_only=False, unsafe here.
            raise GrounderError(
                f"{path}: not a tensor file torch loads safely ({type(exc).__name__}); pass the data's tosses/N.pt"
                " files as saved, float64 tensors of shape (T, 13)"
            ) from exc
        problem = tensor_problem(tensor)
        if problem is not None:  # each would fail in .numpy() below, or lose its imaginary part silently
            raise GrounderError(f"{path}: the toss {problem}; expected a dense real tensor of shape (T, 13)")
        rows = tensor.detach().to(torch.float64).numpy()
        if rows.ndim != 2 or rows.shape[1] != _NUM_COLUMNS or rows.shape[0] < 2:
            raise GrounderError(f"{path}: expected shape (T >= 2, 13), got {tuple(rows.shape)}")
        if not np.isfinite(rows).all():
            raise GrounderError(
                f"{path}: holds NaN or infinite values at row {int(np.argmin(np.isfinite(rows).all(1)))}"
            )
        quat_wxyz = rows[:, 0:4]
        norm = np.linalg.norm(quat_wxyz, axis=1)
        if np.any(np.abs(norm - 1.0) > _QUAT_RENORM_TOL):
            row = int(np.argmax(np.abs(norm - 1.0)))
            raise GrounderError(f"{path}: quaternion at row {row} has norm {norm[row]:.6g}, expected 1")
        qpos = np.concatenate([rows[:, 4:7], quat_wxyz / norm[:, None]], axis=1)
        qvel = np.concatenate([rows[:, 10:13], rows[:, 7:10]], axis=1)
        time_s = np.arange(rows.shape[0], dtype=np.float64) / DAIR_PLL_CUBE_RATE_HZ
        out.append(Trajectory(time_s=time_s, qpos=qpos, qvel=qvel, name=path.stem))
    return out


IMPORTERS: dict[str, Callable[[Path], list[Trajectory]]] = {"dair-pll-cube": load_dair_pll_cube}
"""Importers by ``--format`` name."""


def import_trajectories(fmt: str, src_dir: Path) -> list[Trajectory]:
    """Reads recorded motion in a named format; see :data:`IMPORTERS`.

    Raises:
        GrounderError: the format is unknown, or the importer rejects the input.
    """
    if fmt not in IMPORTERS:
        raise GrounderError(f"unknown trajectory format {fmt!r}; known formats: {', '.join(sorted(IMPORTERS))}")
    return IMPORTERS[fmt](Path(src_dir))
