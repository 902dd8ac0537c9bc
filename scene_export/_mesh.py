"""Validation of the meshes that become rigid bodies, shared by collision geometry and MJCF export."""

from __future__ import annotations

import hashlib

import numpy as np
import trimesh

from scene_export.errors import InvalidMeshError

# A mesh whose volume is below this fraction of its bounding box's volume is flat or degenerate (a sheet, a line).
_MIN_VOLUME_FRACTION_OF_BBOX = 1e-6


def as_mesh_arrays(vertices_m: np.ndarray, faces: np.ndarray, *, what: str) -> tuple[np.ndarray, np.ndarray]:
    """Checks shapes, dtypes, index range and finiteness; returns (V, 3) float64 and (F, 3) int64 copies.

    Raises:
        InvalidMeshError: with a one-line message naming `what` (e.g. "mesh of object 'bowl'").
    """
    vertices = np.asarray(vertices_m)
    faces_arr = np.asarray(faces)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise InvalidMeshError(f"{what}: vertices.shape={vertices.shape} but expected (V, 3) metres")
    if faces_arr.ndim != 2 or faces_arr.shape[1] != 3:
        raise InvalidMeshError(f"{what}: faces.shape={faces_arr.shape} but expected (F, 3) triangle indices")
    if len(vertices) < 4 or len(faces_arr) < 4:
        raise InvalidMeshError(
            f"{what} is empty or degenerate ({len(vertices)} vertices, {len(faces_arr)} faces); a closed solid "
            "needs at least 4 of each: check the segmentation/meshing step that produced it"
        )
    if not np.issubdtype(vertices.dtype, np.number) or np.iscomplexobj(vertices):
        raise InvalidMeshError(f"{what}: vertices have dtype {vertices.dtype} but expected real numbers")
    if not np.issubdtype(faces_arr.dtype, np.integer):
        raise InvalidMeshError(f"{what}: faces have dtype {faces_arr.dtype} but expected integers")
    vertices = np.ascontiguousarray(vertices, dtype=np.float64)
    faces_arr = np.ascontiguousarray(faces_arr, dtype=np.int64)
    bad = ~np.isfinite(vertices).all(axis=1)
    if bad.any():
        raise InvalidMeshError(
            f"{what} has {int(bad.sum())} vertices with NaN or inf (first: index {int(np.flatnonzero(bad)[0])}); "
            "drop or repair them before export"
        )
    if faces_arr.min() < 0 or faces_arr.max() >= len(vertices):
        raise InvalidMeshError(
            f"{what}: face indices span [{faces_arr.min()}, {faces_arr.max()}] but there are {len(vertices)} "
            "vertices (0-based indices expected)"
        )
    return vertices, faces_arr


def mesh_sha256(vertices: np.ndarray, faces: np.ndarray) -> str:
    """Hash of a mesh's exact arrays (float64 vertices, int64 faces), stable across processes and machines."""
    digest = hashlib.sha256()
    for tag, array in (
        (b"vertices_f64", np.ascontiguousarray(vertices, "<f8")),
        (b"faces_i64", np.ascontiguousarray(faces, "<i8")),
    ):
        digest.update(tag + str(array.shape).encode())
        digest.update(array.tobytes())
    return digest.hexdigest()


def solid_trimesh(vertices: np.ndarray, faces: np.ndarray, *, what: str) -> trimesh.Trimesh:
    """A watertight, consistently wound, outward-facing trimesh of positive volume built from validated arrays.

    Vertices at identical positions are merged first, so a visual mesh whose UV seams duplicate vertices still
    counts as closed. An inside-out mesh (negative volume) is inverted rather than rejected.

    Raises:
        InvalidMeshError: not watertight, inconsistent winding, or zero volume.
    """
    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, process=True, validate=False)
    if not mesh.is_watertight:
        boundary = len(trimesh.grouping.group_rows(mesh.edges_sorted, require_count=1))
        raise InvalidMeshError(
            f"{what} is not watertight ({boundary} edges bound a hole, or edges are shared by more than 2 faces); "
            "close it first (e.g. trimesh.repair.fill_holes, or mesh with a closed bottom) so it has a volume"
        )
    if not mesh.is_winding_consistent:
        raise InvalidMeshError(
            f"{what} is closed but its faces are wound inconsistently; fix with trimesh.repair.fix_normals(mesh)"
        )
    bbox_volume = float(np.prod(np.maximum(mesh.extents, 1e-12)))
    with np.errstate(invalid="ignore", divide="ignore"):  # trimesh divides by a zero volume for the centre of mass
        volume = float(mesh.volume)
    if abs(volume) <= max(_MIN_VOLUME_FRACTION_OF_BBOX * bbox_volume, 1e-15):
        raise InvalidMeshError(
            f"{what} has zero volume ({volume:.3g} m^3 inside a {mesh.extents.round(4).tolist()} m box): it is "
            "flat or degenerate; rebuild it as a closed solid"
        )
    if volume < 0:
        mesh.invert()
    return mesh
