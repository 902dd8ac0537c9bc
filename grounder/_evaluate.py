"""Comparing a grounded scene with a ground truth (for synthetic samples and benchmarks)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from grounder.errors import GrounderError

if TYPE_CHECKING:
    import trimesh


@dataclass(frozen=True, kw_only=True)
class ObjectError:
    """How far one grounded object is from the true object it was matched to (world frame, metres)."""

    name: str
    true_name: str
    centre_error_m: float  # bounding-box centres
    chamfer_m: float  # mean of both directed mean surface distances
    extents_m: tuple[float, float, float]
    true_extents_m: tuple[float, float, float]
    volume_ratio: float  # grounded / true

    @property
    def extent_error(self) -> float:
        """Largest relative error over the three world-axis extents."""
        return float(np.max(np.abs(np.array(self.extents_m) / np.array(self.true_extents_m) - 1)))


def _true_meshes(truth_dir: Path) -> dict[str, trimesh.Trimesh]:
    import trimesh

    objects = json.loads((truth_dir / "objects.json").read_text())["objects"]
    out: dict[str, trimesh.Trimesh] = {}
    for obj in objects:
        mesh = trimesh.load_mesh(truth_dir / obj["mesh"])
        w, x, y, z = obj["quat_wxyz"]
        pose = np.eye(4)
        pose[:3, :3] = Rotation.from_quat([x, y, z, w]).as_matrix()
        pose[:3, 3] = obj["pos_m"]
        mesh.apply_transform(pose)
        out[obj["name"]] = mesh
    return out


def _grounded_meshes(scene_dir: Path) -> dict[str, trimesh.Trimesh]:
    import trimesh

    manifest = json.loads((scene_dir / "scene.json").read_text())
    out: dict[str, trimesh.Trimesh] = {}
    for name, obj in manifest["objects"].items():
        mesh = trimesh.load_mesh(scene_dir / obj["visual_mesh"], process=False)
        w, x, y, z = obj["quat_wxyz"]
        pose = np.eye(4)
        pose[:3, :3] = Rotation.from_quat([x, y, z, w]).as_matrix()
        pose[:3, 3] = obj["pos_m"]
        mesh.apply_transform(pose)
        out[name] = mesh
    return out


def compare_to_truth(scene_dir: Path, truth_dir: Path, *, samples: int = 30000, seed: int = 0) -> list[ObjectError]:
    """Matches each grounded object to the nearest true object (by centre) and measures the errors.

    Args:
        scene_dir: a folder written by `ground` (scene.json + assets).
        truth_dir: a sample's truth folder (objects.json + meshes).

    Raises:
        GrounderError: two grounded objects match the same true object.
    """
    truth = _true_meshes(truth_dir)
    grounded = _grounded_meshes(scene_dir)
    rng = np.random.default_rng(seed)
    errors, used = [], set()
    for name, mesh in grounded.items():
        centre = mesh.bounds.mean(axis=0)
        true_name = min(truth, key=lambda n: np.linalg.norm(truth[n].bounds.mean(axis=0) - centre))
        if true_name in used:
            raise GrounderError(f"{name} and another grounded object both match true object {true_name}")
        used.add(true_name)
        true_mesh = truth[true_name]
        a = _sample(mesh, samples, rng)
        b = _sample(true_mesh, samples, rng)
        d_ab, _ = cKDTree(b).query(a)
        d_ba, _ = cKDTree(a).query(b)
        errors.append(
            ObjectError(
                name=name,
                true_name=true_name,
                centre_error_m=float(np.linalg.norm(centre - true_mesh.bounds.mean(axis=0))),
                chamfer_m=float((d_ab.mean() + d_ba.mean()) / 2),
                extents_m=_triple(mesh.extents),
                true_extents_m=_triple(true_mesh.extents),
                volume_ratio=float(mesh.volume / true_mesh.volume),
            )
        )
    return errors


def _triple(values: np.ndarray) -> tuple[float, float, float]:
    return (float(values[0]), float(values[1]), float(values[2]))


def _sample(mesh: trimesh.Trimesh, count: int, rng: np.random.Generator) -> np.ndarray:
    import trimesh

    points, _ = trimesh.sample.sample_surface(mesh, count, seed=int(rng.integers(1 << 31)))
    return np.asarray(points)
