"""MJCF export with `mujoco.MjSpec`: a folder with `scene.xml`, `scene.json` and `assets/` that MuJoCo loads as is.

Conventions (stated once, here):
- World frame: metric, z up, table top at `TableSpec.top_z_m` (the reconstruction's world frame).
- Object frame: the frame of the object's meshes; its pose is `world_from_object` (4x4, metres). Each object is a
  body at that pose with a free joint, so `qpos` = position then quaternion w-first; `qvel` = world linear velocity
  then body-frame angular velocity.
- Geom groups: 0 table and floor, 2 visual meshes (no contacts, no mass), 3 collision hulls (hidden by default).
- Cameras: `world_from_cam` uses OpenCV axes (x right, y down, z forward); MuJoCo cameras look along their -z with
  y up, so the MJCF camera frame is `world_from_cam @ diag(1, -1, -1)`.
"""

from __future__ import annotations

import json
import math
import re
import time
import xml.etree.ElementTree as ET
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import mujoco
import numpy as np

from image2sim_common.outdir import staged_output_dir, write_image
from reconstruction import CameraIntrinsics, TexturedMesh
from scene_export._collision import CollisionGeometry
from scene_export._mesh import as_mesh_arrays, solid_trimesh
from scene_export.errors import (
    CompileError,
    DuplicateNameError,
    InvalidMeshError,
    InvalidSceneSpecError,
    OutputExistsError,
    SceneExportError,
)

MANIFEST_FORMAT = "image2sim.scene/1"
_OPENCV_TO_MUJOCO_CAM = np.diag([1.0, -1.0, -1.0])  # flips y and z: OpenCV (y down, z forward) -> MuJoCo (y up, -z)
_RESERVED_MANIFEST_KEYS = frozenset({"format", "scene_xml", "convention", "objects", "table", "cameras", "options"})


# ---------------------------------------------------------------- typed inputs


def _floats(values: Any, count: int, what: str) -> tuple[float, ...]:
    array = np.asarray(values, dtype=np.float64).reshape(-1)
    if array.shape != (count,) or not np.isfinite(array).all():
        raise InvalidSceneSpecError(f"{what}={values!r} but expected {count} finite numbers")
    return tuple(float(v) for v in array)


def _rigid_transform(matrix: Any, what: str) -> np.ndarray:
    """A read-only float64 copy of a 4x4 rigid transform, after checking it is one (rotation + translation)."""
    pose = np.array(matrix, dtype=np.float64)
    if pose.shape != (4, 4) or not np.isfinite(pose).all():
        raise InvalidSceneSpecError(f"{what}: shape {pose.shape} but expected a finite (4, 4) rigid transform")
    rotation = pose[:3, :3]
    if not np.allclose(pose[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
        raise InvalidSceneSpecError(f"{what}: last row is {pose[3].tolist()} but expected [0, 0, 0, 1]")
    orthogonality = float(np.abs(rotation.T @ rotation - np.eye(3)).max())
    if orthogonality > 1e-5 or np.linalg.det(rotation) <= 0:
        raise InvalidSceneSpecError(
            f"{what}: the upper-left 3x3 is not a rotation (|R^T R - I| = {orthogonality:.2g}, det = "
            f"{np.linalg.det(rotation):.3g}); pass a rigid transform without scale or mirroring"
        )
    pose.setflags(write=False)
    return pose


def _quat_wxyz(rotation: np.ndarray) -> np.ndarray:
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, np.ascontiguousarray(rotation, dtype=np.float64).reshape(-1))
    quat /= np.linalg.norm(quat)
    return quat if quat[0] >= 0 else -quat


@dataclass(frozen=True, kw_only=True)
class SceneObjectSpec:
    """One rigid object to export.

    Attributes:
        name: object name (sanitised to `[A-Za-z0-9_-]` for MJCF and file names; the manifest keeps both).
        visual: watertight textured mesh in the object frame; also the source of mass and inertia.
        collision: convex hulls in the object frame (`convex_decomposition` of the same mesh).
        world_from_object: (4, 4) pose of the object frame in the world, metres.
        density_kg_m3: uniform density; mass = visual mesh volume x density.
        friction: (sliding, torsional, rolling) MuJoCo friction coefficients.
        solref: (timeconst_s, dampratio) of MuJoCo's soft contact; dampratio < 1 makes contacts bouncier.
        solimp: (dmin, dmax, width_m, midpoint, power) impedance of the soft contact.
        condim: contact dimensionality; 6 uses all three friction coefficients.
        rgba: colour of the visual mesh when it has no texture.
    """

    name: str
    visual: TexturedMesh
    collision: CollisionGeometry
    world_from_object: np.ndarray
    density_kg_m3: float = 1000.0
    friction: tuple[float, float, float] = (0.8, 0.005, 0.0001)
    solref: tuple[float, float] = (0.02, 1.0)
    solimp: tuple[float, float, float, float, float] = (0.9, 0.95, 0.001, 0.5, 2.0)
    condim: int = 6
    rgba: tuple[float, float, float, float] = (0.7, 0.7, 0.7, 1.0)

    def __post_init__(self) -> None:
        what = f"object {self.name!r}"
        if not isinstance(self.name, str) or not self.name.strip():
            raise InvalidSceneSpecError(f"object name {self.name!r} but expected a non-empty string")
        object.__setattr__(self, "world_from_object", _rigid_transform(self.world_from_object, f"{what} pose"))
        object.__setattr__(self, "friction", _floats(self.friction, 3, f"{what} friction"))
        object.__setattr__(self, "solref", _floats(self.solref, 2, f"{what} solref"))
        object.__setattr__(self, "solimp", _floats(self.solimp, 5, f"{what} solimp"))
        object.__setattr__(self, "rgba", _floats(self.rgba, 4, f"{what} rgba"))
        if not (math.isfinite(self.density_kg_m3) and self.density_kg_m3 > 0):
            raise InvalidSceneSpecError(f"{what}: density_kg_m3={self.density_kg_m3} but expected > 0 (water: 1000)")
        if min(self.friction) < 0 or self.friction[0] <= 0:
            raise InvalidSceneSpecError(f"{what}: friction={self.friction} but expected sliding > 0, others >= 0")
        if self.solref[0] <= 0 or self.solref[1] <= 0:
            raise InvalidSceneSpecError(f"{what}: solref={self.solref} but expected (timeconst_s > 0, dampratio > 0)")
        if not (0 < self.solimp[0] <= self.solimp[1] < 1 and self.solimp[2] > 0):
            raise InvalidSceneSpecError(f"{what}: solimp={self.solimp} but expected 0 < dmin <= dmax < 1, width > 0")
        if self.condim not in (1, 3, 4, 6):
            raise InvalidSceneSpecError(f"{what}: condim={self.condim} but expected 1, 3, 4 or 6")


@dataclass(frozen=True, kw_only=True)
class TableSpec:
    """The static support: a box whose top face is exactly at `top_z_m`.

    Attributes:
        top_z_m: height of the table top in the world (0 in the reconstruction's world frame).
        half_extents_m: (x, y) half sizes, centred on the world origin.
        thickness_m: box thickness below the top.
        rgba: colour (of the sides, and of the top without `texture_rgb`).
        friction: friction of the table; objects' contact parameters win (their hulls have a higher priority).
        texture_rgb: (H, W, 3) uint8 image of the top face as filmed (row 0 = the +y edge, column 0 = the -x
            edge; `reconstruction.bake_table_texture`), shown on a visual sheet over the top; None: plain colour.
    """

    top_z_m: float = 0.0
    half_extents_m: tuple[float, float] = (0.7, 0.5)
    thickness_m: float = 0.04
    rgba: tuple[float, float, float, float] = (0.55, 0.38, 0.22, 1.0)
    friction: tuple[float, float, float] = (1.0, 0.005, 0.0001)
    texture_rgb: np.ndarray | None = field(default=None, compare=False, repr=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "half_extents_m", _floats(self.half_extents_m, 2, "table half_extents_m"))
        object.__setattr__(self, "rgba", _floats(self.rgba, 4, "table rgba"))
        object.__setattr__(self, "friction", _floats(self.friction, 3, "table friction"))
        texture = self.texture_rgb
        if texture is not None and (texture.ndim != 3 or texture.shape[2] != 3 or texture.dtype != np.uint8):
            raise InvalidSceneSpecError(
                f"table: texture_rgb has shape {texture.shape}, dtype {texture.dtype} but expected (H, W, 3) uint8"
            )
        if min(self.half_extents_m) <= 0 or not self.thickness_m > 0 or not math.isfinite(self.top_z_m):
            raise InvalidSceneSpecError(
                f"table: half_extents_m={self.half_extents_m}, thickness_m={self.thickness_m}, "
                f"top_z_m={self.top_z_m} but expected positive sizes and a finite height"
            )


@dataclass(frozen=True, kw_only=True)
class CameraSpec:
    """A pinhole camera with its principal point at the image centre.

    Attributes:
        name: camera name (sanitised like object names).
        world_from_cam: (4, 4) camera-to-world pose, OpenCV axes (x right, y down, z forward), metres.
        fovy_deg: vertical field of view.
        width_px, height_px: image size.
    """

    name: str
    world_from_cam: np.ndarray
    fovy_deg: float
    width_px: int
    height_px: int

    def __post_init__(self) -> None:
        object.__setattr__(self, "world_from_cam", _rigid_transform(self.world_from_cam, f"camera {self.name!r}"))
        if not 0 < self.fovy_deg < 180 or self.width_px < 1 or self.height_px < 1:
            raise InvalidSceneSpecError(
                f"camera {self.name!r}: fovy_deg={self.fovy_deg}, size {self.width_px}x{self.height_px} px but "
                "expected 0 < fovy < 180 and a positive size"
            )

    @classmethod
    def from_intrinsics(cls, name: str, world_from_cam: np.ndarray, intrinsics: CameraIntrinsics) -> CameraSpec:
        """Vertical field of view and size from pinhole intrinsics (distortion and off-centre principal point,
        typically a few pixels, are ignored)."""
        return cls(
            name=name,
            world_from_cam=world_from_cam,
            fovy_deg=intrinsics.fovy_deg,
            width_px=intrinsics.width_px,
            height_px=intrinsics.height_px,
        )


@dataclass(frozen=True, kw_only=True)
class ExportOptions:
    """Simulation settings written into the MJCF; doubles as the CLI section.

    Attributes:
        timestep_s: physics step.
        integrator: "implicitfast" (stable with stiff contacts and damping), "Euler", "RK4" or "implicit".
        cone: friction cone, "elliptic" (no pyramid anisotropy, less creep at rest) or "pyramidal".
        impratio: ratio of frictional to normal constraint impedance (> 1 reduces slip with elliptic cones).
        floor_z_m: height of an infinite floor plane, or None for none.
        floor_rgba: its colour.
    """

    timestep_s: float = 0.002
    integrator: str = "implicitfast"
    cone: str = "elliptic"
    impratio: float = 1.0
    floor_z_m: float | None = None
    floor_rgba: tuple[float, float, float, float] = (0.4, 0.4, 0.4, 1.0)

    def __post_init__(self) -> None:
        if not 0 < self.timestep_s <= 0.05:
            raise InvalidSceneSpecError(f"{self.timestep_s=} but expected a step in (0, 0.05] s, e.g. 0.002")
        if self.integrator not in _INTEGRATORS:
            raise InvalidSceneSpecError(f"{self.integrator=} but expected one of {sorted(_INTEGRATORS)}")
        if self.cone not in _CONES:
            raise InvalidSceneSpecError(f"{self.cone=} but expected one of {sorted(_CONES)}")
        if not self.impratio >= 1.0:
            raise InvalidSceneSpecError(f"{self.impratio=} but expected >= 1")

    def set_physics(self, option: Any) -> None:
        """Writes the physics settings (time step, integrator, cone, impratio) into an `MjSpec.option`."""
        option.timestep = self.timestep_s
        option.integrator = _INTEGRATORS[self.integrator]
        option.cone = _CONES[self.cone]
        option.impratio = self.impratio


_INTEGRATORS = {
    "Euler": mujoco.mjtIntegrator.mjINT_EULER,
    "RK4": mujoco.mjtIntegrator.mjINT_RK4,
    "implicit": mujoco.mjtIntegrator.mjINT_IMPLICIT,
    "implicitfast": mujoco.mjtIntegrator.mjINT_IMPLICITFAST,
}
_CONES = {"pyramidal": mujoco.mjtCone.mjCONE_PYRAMIDAL, "elliptic": mujoco.mjtCone.mjCONE_ELLIPTIC}


@dataclass(frozen=True, kw_only=True)
class ExportedScene:
    """What `export_scene` wrote.

    Attributes:
        out_dir: the scene folder.
        scene_xml: `out_dir/scene.xml` (asset paths relative to it).
        manifest_json: `out_dir/scene.json`.
        body_names: input object name -> MJCF body name (they differ only when a name had to be sanitised).
        camera_names: input camera name -> MJCF camera name.
        seconds: wall time of the export.
    """

    out_dir: Path
    scene_xml: Path
    manifest_json: Path
    body_names: dict[str, str]
    camera_names: dict[str, str]
    seconds: float


class SettleMotion(NamedTuple):
    """How far a free body moved from its exported pose: origin displacement (m) and rotation angle (deg)."""

    displacement_m: float
    rotation_deg: float


# ---------------------------------------------------------------- names and files


def mjcf_name(raw: str, fallback: str) -> str:
    """A name safe in MJCF attributes and file names: runs of other characters than [A-Za-z0-9_-] become '_'."""
    name = re.sub(r"[^A-Za-z0-9_-]+", "_", raw).strip("_")[:64]
    return name or fallback


def _unique_names(raw_names: Sequence[str], kind: str) -> dict[str, str]:
    seen: dict[str, str] = {}
    mapping: dict[str, str] = {}
    for i, raw in enumerate(raw_names):
        if raw in mapping:
            raise DuplicateNameError(f"two {kind}s are named {raw!r}; {kind} names must be unique: rename one")
        safe = mjcf_name(raw, f"{kind}_{i}")
        if safe in seen:
            raise DuplicateNameError(
                f"{kind}s {seen[safe]!r} and {raw!r} both become {safe!r} in MJCF (only [A-Za-z0-9_-] is kept); "
                "rename one"
            )
        seen[safe] = raw
        mapping[raw] = safe
    return mapping


def _write_obj(path: Path, vertices: np.ndarray, faces: np.ndarray, uv: np.ndarray | None = None) -> None:
    """Writes an OBJ; with `uv`, vertex i has texture coordinate i (OBJ convention, v = 0 is the image's bottom)."""
    lines = [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in vertices]
    if uv is None:
        lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces]
    else:
        lines += [f"vt {u:.9g} {v:.9g}" for u, v in uv]
        lines += [f"f {a + 1}/{a + 1} {b + 1}/{b + 1} {c + 1}/{c + 1}" for a, b, c in faces]
    path.write_text("\n".join(lines) + "\n")


def _write_png_rgb(path: Path, image_rgb: np.ndarray) -> None:
    write_image(path, np.ascontiguousarray(image_rgb[..., ::-1]), error=SceneExportError)


# ---------------------------------------------------------------- export


@dataclass(frozen=True, kw_only=True)
class _MassProperties:
    volume_m3: float
    mass_kg: float
    com_m: np.ndarray  # (3,) centre of mass in the object frame
    inertia_kg_m2: np.ndarray  # (3, 3) inertia tensor about the centre of mass, object-frame axes
    extents_m: np.ndarray  # (3,) axis-aligned extents of the visual mesh in the object frame


def _mass_properties(obj: SceneObjectSpec) -> _MassProperties:
    what = f"visual mesh of object {obj.name!r}"
    vertices, faces = as_mesh_arrays(obj.visual.vertices_m, obj.visual.faces, what=what)
    mesh = solid_trimesh(vertices, faces, what=what)
    mesh.density = obj.density_kg_m3
    return _MassProperties(
        volume_m3=float(mesh.volume),
        mass_kg=float(mesh.mass),
        com_m=np.asarray(mesh.center_mass, dtype=np.float64),
        inertia_kg_m2=np.asarray(mesh.moment_inertia, dtype=np.float64),
        extents_m=np.asarray(mesh.extents, dtype=np.float64),
    )


def _check_visual(obj: SceneObjectSpec) -> None:
    texture = obj.visual.texture_rgb
    if texture is not None and (texture.ndim != 3 or texture.shape[2] != 3 or texture.dtype != np.uint8):
        raise InvalidMeshError(
            f"object {obj.name!r}: texture_rgb has shape {texture.shape}, dtype {texture.dtype} but expected "
            "(H, W, 3) uint8 RGB"
        )
    if obj.visual.uv is not None and not np.isfinite(obj.visual.uv).all():
        raise InvalidMeshError(f"object {obj.name!r}: uv has NaN or inf; recompute the texture coordinates")


def export_scene(
    objects: Sequence[SceneObjectSpec],
    table: TableSpec,
    cameras: Sequence[CameraSpec],
    out_dir: str | Path,
    *,
    options: ExportOptions | None = None,
    manifest_extra: Mapping[str, Any] | None = None,
    overwrite: bool = False,
) -> ExportedScene:
    """Writes `out_dir/scene.xml`, `out_dir/scene.json` and `out_dir/assets/`, then checks MuJoCo loads them.

    Each object becomes a body at `world_from_object` with a free joint, a textured visual mesh (group 2, no
    contacts, no mass) and its convex hulls (group 3) carrying the contact parameters. Mass and inertia come from
    the watertight visual mesh and the density and are set explicitly on the body: MuJoCo would otherwise sum
    the hulls' volumes, which overlap (CoACD pieces share faces and are merged) and double-count mass.

    Args:
        objects: the rigid objects, unique names.
        table: the static support.
        cameras: cameras to add (e.g. the video's), may be empty.
        out_dir: scene folder; built next to it and moved into place at the end.
        options: simulation settings; defaults to `ExportOptions()`.
        manifest_extra: JSON-serialisable provenance merged at the top level of `scene.json`.
        overwrite: replace a non-empty `out_dir` (only once the new scene is complete).

    Raises:
        DuplicateNameError: two objects or cameras share a (sanitised) name.
        InvalidMeshError: a visual mesh cannot give a mass (not watertight, zero volume, NaN).
        InvalidSceneSpecError: `manifest_extra` is not JSON or reuses a reserved key; no objects.
        OutputExistsError: `out_dir` is not empty and `overwrite` is False.
        CompileError: MuJoCo rejects the written scene.
    """
    start = time.perf_counter()
    options = options or ExportOptions()
    out_dir = Path(out_dir)
    if not objects:
        raise InvalidSceneSpecError("no objects to export; pass at least one SceneObjectSpec")
    body_names = _unique_names([o.name for o in objects], "object")
    camera_names = _unique_names([c.name for c in cameras], "camera")
    extra = dict(manifest_extra or {})
    clash = sorted(set(extra) & (_RESERVED_MANIFEST_KEYS | {"versions"}))
    if clash:
        raise InvalidSceneSpecError(f"manifest_extra reuses reserved keys {clash}; nest them under another key")
    try:
        json.dumps(extra)
    except (TypeError, ValueError) as exc:
        raise InvalidSceneSpecError(
            f"manifest_extra is not JSON-serialisable ({exc}); pass plain numbers/strings"
        ) from exc
    for obj in objects:
        _check_visual(obj)
    mass_props = {obj.name: _mass_properties(obj) for obj in objects}

    with staged_output_dir(out_dir, overwrite=overwrite, error=OutputExistsError) as staging:
        assets = staging / "assets"
        assets.mkdir()
        spec = _new_spec(staging, options, cameras)
        _add_table(spec, table, options, assets)
        for cam in cameras:
            rotation = cam.world_from_cam[:3, :3] @ _OPENCV_TO_MUJOCO_CAM
            spec.worldbody.add_camera(
                name=camera_names[cam.name],
                pos=cam.world_from_cam[:3, 3].tolist(),
                quat=_quat_wxyz(rotation).tolist(),
                fovy=float(cam.fovy_deg),
            )
        entries: dict[str, dict[str, Any]] = {}
        exact_bodies: dict[str, dict[str, str]] = {}
        for obj in objects:
            name = body_names[obj.name]
            props = mass_props[obj.name]
            files = _add_object(spec, obj, name, props, assets)
            quat = _quat_wxyz(obj.world_from_object[:3, :3])
            pos = obj.world_from_object[:3, 3]
            exact_bodies[name] = {
                "pos": _exact(pos),
                "quat": _exact(quat),
                "ipos": _exact(props.com_m),
                "mass": repr(props.mass_kg),
                "fullinertia": _exact(_fullinertia(props.inertia_kg_m2)),
            }
            entries[name] = {
                "input_name": obj.name,
                "pos_m": pos.tolist(),
                "quat_wxyz": quat.tolist(),
                "extents_m": props.extents_m.tolist(),
                "volume_m3": props.volume_m3,
                "mass_kg": props.mass_kg,
                "com_m": props.com_m.tolist(),
                "inertia_kg_m2": props.inertia_kg_m2.tolist(),
                "density_kg_m3": float(obj.density_kg_m3),
                "friction": list(obj.friction),
                "solref": list(obj.solref),
                "solimp": list(obj.solimp),
                "condim": obj.condim,
                "num_hulls": len(obj.collision.hulls),
                "max_hull_vertices": max(len(h) for h in obj.collision.hulls),
                "collision_method": obj.collision.method,
                "collision_seconds": round(obj.collision.seconds, 4),
                "mesh_sha256": obj.collision.mesh_sha256,
                **files,
            }
        xml = _with_exact_bodies(_to_xml(spec), exact_bodies)
        scene_xml = staging / "scene.xml"
        scene_xml.write_text(xml)
        _load_model(scene_xml)  # compile check of exactly what was written
        manifest = {
            "format": MANIFEST_FORMAT,
            "scene_xml": "scene.xml",
            "convention": "world: metres, z up, table top at table.top_z_m; object pose = body pose (pos_m, "
            "quat_wxyz) of the object frame; inertia_kg_m2 about com_m (object frame); free joints: qpos = pos, "
            "quat wxyz; qvel = world linear velocity, body angular velocity",
            "objects": entries,
            "table": {
                **{k: v for k, v in asdict(table).items() if k != "texture_rgb"},
                "texture": None if table.texture_rgb is None else f"assets/{TABLE_TEXTURE_FILE}",
            },
            "cameras": {
                camera_names[c.name]: {
                    "input_name": c.name,
                    "world_from_cam": c.world_from_cam.tolist(),
                    "fovy_deg": c.fovy_deg,
                    "width_px": c.width_px,
                    "height_px": c.height_px,
                }
                for c in cameras
            },
            "options": asdict(options),
            "versions": _versions(),
            **extra,
        }
        (staging / "scene.json").write_text(json.dumps(manifest, indent=1) + "\n")
    return ExportedScene(
        out_dir=out_dir,
        scene_xml=out_dir / "scene.xml",
        manifest_json=out_dir / "scene.json",
        body_names=body_names,
        camera_names=camera_names,
        seconds=time.perf_counter() - start,
    )


def _new_spec(staging: Path, options: ExportOptions, cameras: Sequence[CameraSpec]) -> mujoco.MjSpec:
    spec = mujoco.MjSpec()
    spec.modelname = "image2sim_scene"
    spec.modelfiledir = str(staging)  # asset paths stay relative to scene.xml
    spec.meshdir = "assets"
    spec.texturedir = "assets"
    options.set_physics(spec.option)
    spec.visual.global_.offwidth = max([1280, *(c.width_px for c in cameras)])
    spec.visual.global_.offheight = max([960, *(c.height_px for c in cameras)])
    spec.visual.headlight.ambient = [0.25, 0.25, 0.25]
    spec.visual.headlight.diffuse = [0.35, 0.35, 0.35]
    world = spec.worldbody
    world.add_light(name="key", pos=[0.6, -0.4, 1.6], dir=[-0.35, 0.25, -1.0], diffuse=[0.6, 0.6, 0.6], castshadow=True)
    world.add_light(name="fill", pos=[-0.8, 0.6, 1.4], dir=[0.5, -0.3, -1.0], diffuse=[0.3, 0.3, 0.3], castshadow=False)
    return spec


TABLE_TEXTURE_FILE = "table_texture.png"
TABLE_SHEET_M = 0.0002  # the textured sheet's thickness over the top face (visual only; objects rest on the box)


def _add_table(spec: mujoco.MjSpec, table: TableSpec, options: ExportOptions, assets: Path) -> None:
    hx, hy = table.half_extents_m
    if table.texture_rgb is not None:
        _write_png_rgb(assets / TABLE_TEXTURE_FILE, table.texture_rgb)
        spec.add_texture(name="table_top", type=mujoco.mjtTexture.mjTEXTURE_2D, file=TABLE_TEXTURE_FILE)
        material = spec.add_material(name="table_top", specular=0.1)
        material.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = "table_top"
        # A thin box whose top carries the image once: OBJ v = 1 is the image's top row (the +y edge).
        z0, z1 = table.top_z_m, table.top_z_m + TABLE_SHEET_M
        top = np.array([[-hx, -hy, z1], [hx, -hy, z1], [hx, hy, z1], [-hx, hy, z1]])
        vertices = np.concatenate([top, top - [0.0, 0.0, z1 - z0]])
        uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]] * 2, float)
        faces = [[0, 1, 2], [0, 2, 3], [4, 6, 5], [4, 7, 6]]
        faces += [[0, 4, 5], [0, 5, 1], [1, 5, 6], [1, 6, 2], [2, 6, 7], [2, 7, 3], [3, 7, 4], [3, 4, 0]]
        _write_obj(assets / "table_top.obj", vertices, np.array(faces), uv)
        spec.add_mesh(name="table_top", file="table_top.obj")
        spec.worldbody.add_geom(
            name="table_top",
            type=mujoco.mjtGeom.mjGEOM_MESH,
            meshname="table_top",
            material="table_top",
            contype=0,
            conaffinity=0,
            group=0,
        )
    spec.worldbody.add_geom(
        name="table",
        type=mujoco.mjtGeom.mjGEOM_BOX,
        size=[hx, hy, table.thickness_m / 2],
        pos=[0.0, 0.0, table.top_z_m - table.thickness_m / 2],  # top face exactly at top_z_m
        rgba=list(table.rgba),
        friction=list(table.friction),
        group=0,
    )
    if options.floor_z_m is not None:
        spec.worldbody.add_geom(
            name="floor",
            type=mujoco.mjtGeom.mjGEOM_PLANE,
            size=[0.0, 0.0, 0.05],  # 0 = infinite plane
            pos=[0.0, 0.0, options.floor_z_m],
            rgba=list(options.floor_rgba),
            group=0,
        )


def _add_object(
    spec: mujoco.MjSpec, obj: SceneObjectSpec, name: str, props: _MassProperties, assets: Path
) -> dict[str, Any]:
    """Adds the object's assets, body, free joint, visual geom and hull geoms; returns the file names written."""
    visual_file = f"{name}_visual.obj"
    _write_obj(assets / visual_file, obj.visual.vertices_m, obj.visual.faces, obj.visual.uv)
    spec.add_mesh(name=f"{name}_visual", file=visual_file)
    material = spec.add_material(name=name, specular=0.3)
    texture_file = None
    if obj.visual.texture_rgb is not None:
        texture_file = f"{name}_texture.png"  # MuJoCo reads PNG textures; the image's top row is v = 1 in the OBJ
        _write_png_rgb(assets / texture_file, obj.visual.texture_rgb)
        spec.add_texture(name=name, type=mujoco.mjtTexture.mjTEXTURE_2D, file=texture_file)
        material.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = name
    else:
        material.rgba = list(obj.rgba)

    body = spec.worldbody.add_body(
        name=name,
        pos=obj.world_from_object[:3, 3].tolist(),
        quat=_quat_wxyz(obj.world_from_object[:3, :3]).tolist(),
    )
    body.add_freejoint(name=f"{name}_free")
    # Mass and inertia are the visual (watertight) mesh's, set explicitly: MuJoCo would otherwise add up the
    # geoms' own masses, and the collision hulls overlap (CoACD merges pieces, hull vertices are reduced), so their
    # summed volume over-counts (by ~50% on the sample bowl). Every geom therefore has density 0.
    body.explicitinertial = True
    body.mass = props.mass_kg
    body.ipos = props.com_m.tolist()
    body.fullinertia = _fullinertia(props.inertia_kg_m2).tolist()
    body.add_geom(
        name=f"{name}_visual",
        type=mujoco.mjtGeom.mjGEOM_MESH,
        meshname=f"{name}_visual",
        material=name,
        group=2,
        contype=0,
        conaffinity=0,
        density=0.0,
    )
    hull_files = []
    for i, hull in enumerate(obj.collision.hulls):
        hull_file = f"{name}_hull_{i:02d}.obj"
        _write_obj(assets / hull_file, *_hull_mesh(hull))
        hull_files.append(hull_file)
        mesh = spec.add_mesh(name=f"{name}_hull_{i:02d}", file=hull_file)
        mesh.maxhullvert = max(4, len(hull))
        body.add_geom(
            name=f"{name}_hull_{i:02d}",
            type=mujoco.mjtGeom.mjGEOM_MESH,
            meshname=f"{name}_hull_{i:02d}",
            group=3,
            contype=1,
            conaffinity=1,
            condim=obj.condim,
            # priority 1 beats the table's 0: this object's friction/solref/solimp govern its contacts with the
            # table instead of MuJoCo's default mix (max friction), so the calibrated values mean what they say.
            priority=1,
            friction=list(obj.friction),
            solref=list(obj.solref),
            solimp=list(obj.solimp),
            density=0.0,
            rgba=[0.3, 0.7, 0.3, 0.5],
        )
    return {
        "visual_mesh": f"assets/{visual_file}",
        "texture": None if texture_file is None else f"assets/{texture_file}",
        "hull_meshes": [f"assets/{f}" for f in hull_files],
    }


def _hull_mesh(hull: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and outward triangles of a convex hull (MuJoCo recomputes the hull; the faces are for viewers)."""
    import trimesh

    mesh = trimesh.convex.convex_hull(hull)
    return np.asarray(mesh.vertices), np.asarray(mesh.faces)


def _fullinertia(inertia: np.ndarray) -> np.ndarray:
    """MJCF `fullinertia` order: (Ixx, Iyy, Izz, Ixy, Ixz, Iyz) of the symmetric inertia tensor."""
    return np.array([inertia[0, 0], inertia[1, 1], inertia[2, 2], inertia[0, 1], inertia[0, 2], inertia[1, 2]])


def _exact(values: np.ndarray) -> str:
    return " ".join(repr(float(v)) for v in values)


def _to_xml(spec: mujoco.MjSpec) -> str:
    try:
        return spec.to_xml()
    except Exception as exc:
        raise CompileError(f"MuJoCo could not build the scene ({exc}); check the meshes and names above") from exc


def _with_exact_bodies(xml: str, exact: dict[str, dict[str, str]]) -> str:
    """Rewrites object body poses and inertials at full float precision.

    `MjSpec.to_xml` prints 6 significant digits (mass off by up to 5e-6 relative, and the inertia diagonalised
    into a rounded quaternion); the manifest and the calibration downstream need what was computed.
    """
    root = ET.fromstring(xml)
    worldbody = root.find("worldbody")
    assert worldbody is not None
    for body in worldbody.findall("body"):
        values = exact.get(body.get("name", ""))
        if values is None:
            continue
        body.set("pos", values["pos"])
        body.set("quat", values["quat"])
        inertial = body.find("inertial")
        assert inertial is not None, "MjSpec wrote no <inertial> for a body with explicit inertia"
        for key in list(inertial.attrib):
            del inertial.attrib[key]
        inertial.set("pos", values["ipos"])
        inertial.set("mass", values["mass"])
        inertial.set("fullinertia", values["fullinertia"])
    ET.indent(root, space="  ")
    return ET.tostring(root, encoding="unicode") + "\n"


def _versions() -> dict[str, str]:
    from importlib.metadata import PackageNotFoundError, version

    out = {"mujoco": mujoco.__version__, "numpy": np.__version__}
    for package in ("coacd", "trimesh"):
        try:
            out[package] = version(package)
        except PackageNotFoundError:
            out[package] = "not installed"
    return out


# ---------------------------------------------------------------- using an exported scene


def _load_model(scene_xml: Path) -> mujoco.MjModel:
    if not Path(scene_xml).is_file():
        raise CompileError(f"scene file {scene_xml} does not exist; export it first with export_scene()")
    try:
        return mujoco.MjModel.from_xml_path(str(scene_xml))
    except Exception as exc:
        message = " ".join(str(exc).split())
        raise CompileError(f"MuJoCo cannot load {scene_xml}: {message}") from exc


def render_view(scene_xml: str | Path, camera: CameraSpec) -> np.ndarray:
    """Renders the scene at its initial state from `camera` (set `MUJOCO_GL=osmesa` on headless machines).

    Args:
        scene_xml: an exported `scene.xml` (or any MJCF whose assets resolve relative to it).
        camera: pose (OpenCV axes), vertical field of view and image size.

    Returns:
        (height_px, width_px, 3) uint8 RGB image; geom groups 0-2 shown (table, visual meshes), hulls hidden.
    """
    scene_xml = Path(scene_xml)
    _load_model(scene_xml)  # a clear error for a missing or broken file before MjSpec's
    spec = mujoco.MjSpec.from_file(str(scene_xml))
    spec.visual.global_.offwidth = max(spec.visual.global_.offwidth, camera.width_px)
    spec.visual.global_.offheight = max(spec.visual.global_.offheight, camera.height_px)
    rotation = camera.world_from_cam[:3, :3] @ _OPENCV_TO_MUJOCO_CAM
    spec.worldbody.add_camera(
        name="__image2sim_render_view",
        pos=camera.world_from_cam[:3, 3].tolist(),
        quat=_quat_wxyz(rotation).tolist(),
        fovy=float(camera.fovy_deg),
    )
    try:
        model = spec.compile()
    except Exception as exc:
        raise CompileError(f"MuJoCo cannot compile {scene_xml} for rendering: {exc}") from exc
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    renderer = mujoco.Renderer(model, camera.height_px, camera.width_px)
    try:
        renderer.update_scene(data, camera="__image2sim_render_view")
        return np.ascontiguousarray(renderer.render()[:, :, :3])
    finally:
        renderer.close()


def write_preview(path: str | Path, frame_bgr: np.ndarray, rendered_rgb: np.ndarray) -> Path:
    """Writes the input frame and the MuJoCo rendering side by side, captioned "input frame" and "MuJoCo".

    Args:
        path: output image (PNG or JPEG by extension).
        frame_bgr: (H, W, 3) uint8 video frame, OpenCV channel order.
        rendered_rgb: (h, w, 3) uint8 rendering (as from `render_view`); resized to the frame's height.
    """
    import cv2

    path = Path(path)
    for image, what in ((frame_bgr, "frame_bgr"), (rendered_rgb, "rendered_rgb")):
        if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
            raise InvalidSceneSpecError(
                f"{what}: shape {image.shape}, dtype {image.dtype} but expected (H, W, 3) uint8"
            )
    height = frame_bgr.shape[0]
    rendered_bgr = np.ascontiguousarray(rendered_rgb[..., ::-1])
    if rendered_bgr.shape[0] != height:
        width = round(rendered_bgr.shape[1] * height / rendered_bgr.shape[0])
        rendered_bgr = cv2.resize(rendered_bgr, (width, height), interpolation=cv2.INTER_AREA)
    panels = []
    for image, caption in ((frame_bgr, "input frame"), (rendered_bgr, "MuJoCo")):
        panel = image.copy()
        scale = max(0.5, height / 600)
        cv2.rectangle(panel, (0, 0), (panel.shape[1], int(34 * scale)), (0, 0, 0), -1)
        cv2.putText(
            panel, caption, (8, int(25 * scale)), cv2.FONT_HERSHEY_SIMPLEX, 0.8 * scale, (255, 255, 255), 2, cv2.LINE_AA
        )
        panels.append(panel)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_image(path, np.concatenate(panels, axis=1), error=SceneExportError)  # a full disk: says what to free
    return path


def settle_test(scene_xml: str | Path, seconds: float = 2.0) -> dict[str, SettleMotion]:
    """Simulates the scene from rest and measures how far each free body moved from its start.

    A well-placed, well-meshed object at rest should barely move (sub-millimetre contact penetration); a large
    motion means it was floating, interpenetrating or unstable.

    Args:
        scene_xml: an exported `scene.xml`.
        seconds: simulated time.

    Returns:
        Body name -> (displacement of the body origin in metres, rotation angle in degrees), free bodies only.
    """
    if not (math.isfinite(seconds) and seconds > 0):
        raise InvalidSceneSpecError(f"{seconds=} but expected a positive duration in seconds")
    model = _load_model(Path(scene_xml))
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    bodies = [
        b
        for b in range(1, model.nbody)
        if model.body_jntnum[b] == 1 and model.jnt_type[model.body_jntadr[b]] == mujoco.mjtJoint.mjJNT_FREE
    ]
    start_pos = data.xpos[bodies].copy()
    start_quat = data.xquat[bodies].copy()
    for _ in range(round(seconds / model.opt.timestep)):
        mujoco.mj_step(model, data)
    motion = {}
    for k, b in enumerate(bodies):
        # The angle of the relative rotation: 2 acos(|<q0, q1>|) for unit quaternions.
        dot = min(1.0, abs(float(np.dot(start_quat[k], data.xquat[b]))))
        motion[model.body(b).name] = SettleMotion(
            displacement_m=float(np.linalg.norm(data.xpos[b] - start_pos[k])),
            rotation_deg=float(np.rad2deg(2 * np.arccos(dot))),
        )
    return motion
