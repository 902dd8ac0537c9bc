"""Procedural textures, meshes and the MuJoCo scene shared by the sample generators.

The samples are rendered by MuJoCo so that every number in their ground truth is exact. World frame = the ArUco
marker frame: origin at the marker's centre, x to the marker's right, y to its top, z up; the table top is z = 0.
Textures are files (MJCF cannot store in-memory textures) and carry multi-scale detail so SIFT finds features,
with appearance tied to material (wood grain, printed cardboard, painted metal, glazed ceramic).
"""

from __future__ import annotations

import json
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import mujoco
import numpy as np
import trimesh

from image2sim_common.rotations import look_at_world_from_cam

TABLE_HALF_EXTENTS_M = (0.7, 0.5)
TABLE_THICKNESS_M = 0.04
MARKER_SIZE_M = 0.12  # side of the black square
MARKER_MARGIN_M = 0.02  # white border on each side
MARKER_THICKNESS_M = 0.0003  # a printed sheet; its top is the marker frame's z = 0.0003 m above the table
ARUCO_DICT = cv2.aruco.DICT_4X4_50
ARUCO_ID = 0


@dataclass(frozen=True, kw_only=True)
class SampleObject:
    """One rigid object of a sample scene; its mesh is expressed in the object frame (origin at the bbox centre)."""

    name: str
    mesh: trimesh.Trimesh
    texture: str  # texture file name in the assets folder
    pos_m: tuple[float, float, float]  # world position of the object frame
    yaw_deg: float
    density_kg_m3: float
    friction: tuple[float, float, float]  # sliding, torsional, rolling
    solref: tuple[float, float]  # (timeconst_s, dampratio): sets restitution in MuJoCo's soft contact
    material: str
    rgba: tuple[float, float, float, float] = (1.0, 1.0, 1.0, 1.0)
    extra: dict[str, float] = field(default_factory=dict)

    @property
    def quat_wxyz(self) -> np.ndarray:
        return yaw_quat_wxyz(self.yaw_deg)


def yaw_quat_wxyz(yaw_deg: float) -> np.ndarray:
    """Quaternion (w, x, y, z) of a rotation by `yaw_deg` about the world z axis."""
    half = np.deg2rad(yaw_deg) / 2.0
    return np.array([np.cos(half), 0.0, 0.0, np.sin(half)])


# ---------------------------------------------------------------- textures


def _blob_noise(rng: np.random.Generator, size: int, scales: tuple[float, ...]) -> np.ndarray:
    """Sum of Gaussian-smoothed white noise at several scales, normalised to [0, 1]: blobs SIFT can key on."""
    out = np.zeros((size, size), np.float32)
    for sigma in scales:
        layer = cv2.GaussianBlur(rng.standard_normal((size, size)).astype(np.float32), (0, 0), sigma)
        out += layer / (layer.std() + 1e-9)
    out -= out.min()
    return out / (out.max() + 1e-9)


def wood_texture(rng: np.random.Generator, size: int = 1024) -> np.ndarray:
    """Light oak: stretched grain rings plus knots and blotches (BGR uint8)."""
    y, x = np.mgrid[0:size, 0:size].astype(np.float32) / size
    warp = _blob_noise(rng, size, (40.0, 90.0))
    rings = 0.5 + 0.5 * np.sin(2 * np.pi * (y * 14.0 + 3.0 * warp + 0.15 * np.sin(6 * np.pi * x)))
    fine = _blob_noise(rng, size, (1.5, 3.0, 6.0))
    blotch = _blob_noise(rng, size, (12.0, 24.0))
    shade = 0.45 * rings + 0.3 * fine + 0.25 * blotch
    base = np.array([70, 125, 185], np.float32)  # BGR light brown
    dark = np.array([30, 60, 110], np.float32)
    img = base[None, None] * (1 - shade[..., None]) + dark[None, None] * shade[..., None]
    return np.clip(img, 0, 255).astype(np.uint8)


def floor_texture(rng: np.random.Generator, size: int = 512) -> np.ndarray:
    """Grey speckled concrete (BGR uint8)."""
    n = _blob_noise(rng, size, (1.0, 3.0, 8.0))
    img = (90 + 80 * n)[..., None].repeat(3, axis=2)
    return np.clip(img, 0, 255).astype(np.uint8)


def _scribble(img: np.ndarray, rng: np.random.Generator, n: int, palette: list[tuple[int, int, int]]) -> None:
    """Draws printed marks: words, circles, bars; the kind of detail packaging and labels carry."""
    size = img.shape[0]
    words = [
        "FRAGILE",
        "THIS SIDE UP",
        "NO. 42",
        "IMAGE2SIM",
        "LOT 7A",
        "MADE IN",
        "KEEP DRY",
        "250g",
        "REF 3",
    ]
    for _ in range(n):
        color = palette[int(rng.integers(len(palette)))]
        kind = rng.integers(3)
        x, y = (int(v) for v in rng.integers(0, size, 2))
        if kind == 0:
            cv2.putText(
                img,
                words[int(rng.integers(len(words)))],
                (x - size // 8, y),
                cv2.FONT_HERSHEY_SIMPLEX,
                float(rng.uniform(0.6, 1.6)) * size / 512,
                color,
                int(rng.integers(2, 5)),
                cv2.LINE_AA,
            )
        elif kind == 1:
            cv2.circle(img, (x, y), int(rng.integers(8, 40)) * size // 512, color, -1, cv2.LINE_AA)
        else:
            w, h = (int(v) * size // 512 for v in rng.integers(10, 70, 2))
            cv2.rectangle(img, (x, y), (x + w, y + h), color, -1)


def cardboard_texture(rng: np.random.Generator, size: int = 512) -> np.ndarray:
    """Corrugated brown cardboard with print (BGR uint8)."""
    fibre = _blob_noise(rng, size, (1.0, 2.5, 10.0))
    base = np.array([80, 140, 190], np.float32) * (0.8 + 0.35 * fibre[..., None])
    img = np.clip(base, 0, 255).astype(np.uint8)
    _scribble(img, rng, 40, [(20, 20, 20), (30, 30, 160), (120, 60, 20)])
    return img


def label_texture(rng: np.random.Generator, size: int = 512) -> np.ndarray:
    """A painted tin label: colour bands, text and dots (BGR uint8)."""
    img = np.zeros((size, size, 3), np.uint8)
    bands = [(40, 40, 200), (240, 240, 240), (200, 120, 30), (40, 180, 230)]
    edges = np.sort(rng.integers(0, size, 6))
    start = 0
    for i, stop in enumerate([*edges, size]):
        img[start:stop] = bands[i % len(bands)]
        start = stop
    grain = _blob_noise(rng, size, (1.0, 4.0))
    img = np.clip(img.astype(np.float32) * (0.8 + 0.3 * grain[..., None]), 0, 255).astype(np.uint8)
    _scribble(img, rng, 45, [(10, 10, 10), (250, 250, 250), (20, 120, 20)])
    return img


def ceramic_texture(rng: np.random.Generator, size: int = 512) -> np.ndarray:
    """Glazed stoneware: blue-white glaze with brush dots and speckle (BGR uint8)."""
    glaze = _blob_noise(rng, size, (6.0, 20.0))
    base = np.array([200, 170, 120], np.float32)[None, None] * (0.75 + 0.35 * glaze[..., None])
    img = np.clip(base, 0, 255).astype(np.uint8)
    for _ in range(140):
        x, y = (int(v) for v in rng.integers(0, size, 2))
        r = int(rng.integers(3, 14))
        color = [(120, 40, 10), (240, 240, 240), (40, 40, 90)][int(rng.integers(3))]
        cv2.circle(img, (x, y), r, color, -1, cv2.LINE_AA)
    speck = rng.random((size, size)) < 0.01
    img[speck] = (30, 30, 30)
    return img


def marker_texture(
    pixels_per_m: float = 4000.0,
    marker_id: int = ARUCO_ID,
    size_m: float = MARKER_SIZE_M,
    margin_m: float = MARKER_MARGIN_M,
) -> np.ndarray:
    """ArUco DICT_4X4_50 marker (the table's, id 0, by default) with its white margin; the image's top is the
    marker's +y (BGR uint8)."""
    dictionary = cv2.aruco.getPredefinedDictionary(ARUCO_DICT)
    inner_px = round(size_m * pixels_per_m)
    margin_px = round(margin_m * pixels_per_m)
    marker = cv2.aruco.generateImageMarker(dictionary, marker_id, inner_px)
    marker = cv2.copyMakeBorder(marker, *(4 * [margin_px]), cv2.BORDER_CONSTANT, value=255)
    return cv2.cvtColor(marker, cv2.COLOR_GRAY2BGR)


# ---------------------------------------------------------------- meshes


def bowl_mesh(
    *,
    outer_radius_m: float = 0.075,
    height_m: float = 0.055,
    wall_m: float = 0.006,
    foot_radius_m: float = 0.04,
) -> trimesh.Trimesh:
    """A watertight bowl made by revolving a closed (r, z) profile: flat foot, curved wall, open top."""
    t = np.linspace(0.0, 1.0, 12)
    outer_r = foot_radius_m + (outer_radius_m - foot_radius_m) * np.sin(t * np.pi / 2)
    outer_z = height_m * (1 - np.cos(t * np.pi / 2))
    inner_r = np.maximum(outer_r[::-1] - wall_m, 0.0)
    inner_z = np.maximum(outer_z[::-1], wall_m)
    inner_z[-1] = wall_m
    profile = np.concatenate(
        [[[0.0, 0.0]], np.stack([outer_r, outer_z], 1), np.stack([inner_r, inner_z], 1)[1:], [[0.0, wall_m]]]
    )
    mesh = trimesh.creation.revolve(profile, sections=48)
    mesh.merge_vertices()
    if mesh.volume < 0:
        mesh.invert()
    return mesh


def centred(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Moves the mesh so its bounding-box centre is the origin (the object frame used in all truths)."""
    out = mesh.copy()
    out.apply_translation(-out.bounds.mean(axis=0))
    return out


def default_objects() -> list[SampleObject]:
    """The three tabletop objects: a printed box, a tin can and a (concave) ceramic bowl."""
    box = centred(trimesh.creation.box(extents=(0.12, 0.08, 0.06)))
    can = centred(trimesh.creation.cylinder(radius=0.035, height=0.11, sections=48))
    bowl = centred(bowl_mesh())
    return [
        SampleObject(
            name="box",
            mesh=box,
            texture="cardboard.png",
            pos_m=(0.20, 0.12, 0.03),
            yaw_deg=25.0,
            density_kg_m3=180.0,
            friction=(0.55, 0.005, 0.0001),
            solref=(0.02, 1.0),
            material="cardboard",
        ),
        SampleObject(
            name="can",
            mesh=can,
            texture="label.png",
            pos_m=(-0.17, 0.15, 0.055),
            yaw_deg=-40.0,
            density_kg_m3=900.0,
            friction=(0.35, 0.005, 0.0001),
            solref=(0.02, 0.6),
            material="metal",
        ),
        SampleObject(
            name="bowl",
            mesh=bowl,
            texture="ceramic.png",
            pos_m=(-0.03, -0.19, bowl.extents[2] / 2),
            yaw_deg=10.0,
            density_kg_m3=2300.0,
            friction=(0.45, 0.005, 0.0001),
            solref=(0.02, 0.5),
            material="ceramic",
        ),
    ]


def write_obj_with_uv(path: Path, vertices: np.ndarray, uv: np.ndarray, faces: np.ndarray) -> None:
    """Writes an OBJ where vertex i has texture coordinate i (MuJoCo reads `vt` for 2D textures)."""
    lines = [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in vertices]
    lines += [f"vt {u:.6f} {v:.6f}" for u, v in uv]
    lines += [f"f {a + 1}/{a + 1} {b + 1}/{b + 1} {c + 1}/{c + 1}" for a, b, c in faces]
    path.write_text("\n".join(lines) + "\n")


def write_marker_mesh(
    path: Path,
    size_m: float = MARKER_SIZE_M,
    margin_m: float = MARKER_MARGIN_M,
    thickness_m: float = MARKER_THICKNESS_M,
) -> None:
    """A thin sheet; the top face carries the marker image upright (image top = +y), corners in UV (0..1)."""
    h = size_m / 2 + margin_m
    z0, z1 = 0.0, thickness_m
    top = np.array([[-h, -h, z1], [h, -h, z1], [h, h, z1], [-h, h, z1]])
    bottom = top.copy()
    bottom[:, 2] = z0
    vertices = np.concatenate([top, bottom])
    # OBJ/OpenGL v = 0 is the bottom row of the image; MuJoCo flips images so v=1 is the top row.
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]] * 2, float)
    top_bottom = [[0, 1, 2], [0, 2, 3], [4, 6, 5], [4, 7, 6]]
    sides = [[0, 4, 5], [0, 5, 1], [1, 5, 6], [1, 6, 2], [2, 6, 7], [2, 7, 3], [3, 7, 4], [3, 4, 0]]
    faces = np.array(top_bottom + sides)
    write_obj_with_uv(path, vertices, uv, faces)


def write_assets(assets_dir: Path, objects: list[SampleObject], seed: int = 0) -> None:
    """Writes every texture and mesh the scene refers to."""
    assets_dir.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    cv2.imwrite(str(assets_dir / "wood.png"), wood_texture(rng))
    cv2.imwrite(str(assets_dir / "floor.png"), floor_texture(rng))
    cv2.imwrite(str(assets_dir / "cardboard.png"), cardboard_texture(rng))
    cv2.imwrite(str(assets_dir / "label.png"), label_texture(rng))
    cv2.imwrite(str(assets_dir / "ceramic.png"), ceramic_texture(rng))
    cv2.imwrite(str(assets_dir / "marker.png"), marker_texture())
    write_marker_mesh(assets_dir / "marker.obj")
    for obj in objects:
        obj.mesh.export(assets_dir / f"{obj.name}.obj")


def build_scene_spec(
    assets_dir: Path, objects: list[SampleObject], *, free_objects: bool, timestep_s: float = 0.001
) -> mujoco.MjSpec:
    """The true scene: floor, table (top at z = 0), marker sheet, objects, lights and one movable camera.

    Args:
        assets_dir: folder holding the files written by `write_assets`; the MJCF refers to it relatively.
        objects: the objects to place.
        free_objects: give each object a free joint (toss sample) or weld it to the world (static scan).
        timestep_s: physics step.
    """
    spec = mujoco.MjSpec()
    spec.modelname = "image2sim_sample"
    spec.modelfiledir = str(assets_dir.parent)  # asset paths stay relative to the scene file
    spec.meshdir = assets_dir.name
    spec.texturedir = assets_dir.name
    spec.option.timestep = timestep_s
    spec.visual.global_.offwidth = 1280
    spec.visual.global_.offheight = 960
    spec.visual.quality.shadowsize = 4096
    spec.visual.headlight.ambient = [0.25, 0.25, 0.25]
    spec.visual.headlight.diffuse = [0.35, 0.35, 0.35]

    def texture_2d(name: str, file: str) -> None:
        spec.add_texture(name=name, type=mujoco.mjtTexture.mjTEXTURE_2D, file=file)

    def texture_cube(name: str, file: str) -> None:
        spec.add_texture(name=name, type=mujoco.mjtTexture.mjTEXTURE_CUBE, file=file)

    texture_2d("wood", "wood.png")
    texture_2d("floor", "floor.png")
    texture_2d("marker", "marker.png")
    for obj in objects:
        texture_cube(obj.name, obj.texture)
    for name, repeat, uniform in (
        ("wood", (1, 1), False),
        ("floor", (3, 3), True),
        ("marker", (1, 1), False),
    ):
        mat = spec.add_material(name=name, texrepeat=repeat, texuniform=uniform, specular=0.2)
        mat.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = name
    for obj in objects:
        spec_mat = spec.add_material(name=obj.name, specular=0.4 if obj.material in ("metal", "ceramic") else 0.1)
        spec_mat.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = obj.name
        # Exact inertia: MuJoCo's default ("legacy") integrates the convex hull, which made the bowl 6.8x too heavy.
        spec.add_mesh(name=obj.name, file=f"{obj.name}.obj", inertia=mujoco.mjtMeshInertia.mjMESH_INERTIA_EXACT)
    spec.add_mesh(name="marker", file="marker.obj")

    world = spec.worldbody
    world.add_light(name="key", pos=[0.6, -0.4, 1.6], dir=[-0.35, 0.25, -1.0], diffuse=[0.6, 0.6, 0.6], castshadow=True)
    world.add_light(name="fill", pos=[-0.8, 0.6, 1.4], dir=[0.5, -0.3, -1.0], diffuse=[0.3, 0.3, 0.3], castshadow=False)
    add_floor_and_table(world, top_material="wood", marker=True)
    for obj in objects:
        body = world.add_body(name=obj.name, pos=list(obj.pos_m), quat=list(obj.quat_wxyz))
        if free_objects:
            body.add_freejoint(name=f"{obj.name}_free")
        body.add_geom(
            name=f"{obj.name}_geom",
            type=mujoco.mjtGeom.mjGEOM_MESH,
            meshname=obj.name,
            material=obj.name,
            density=obj.density_kg_m3,
            friction=list(obj.friction),
            solref=list(obj.solref),
            condim=6,
        )
    world.add_camera(name="video", pos=[0, -0.6, 0.45], fovy=50.0)
    return spec


def add_floor_and_table(world: mujoco.MjsBody, *, top_material: str, marker: bool) -> None:
    """The static scene under the objects: a floor 0.75 m down, the table (a box for collisions and the sides, and
    a plane exactly on its top face carrying `top_material`) and, with `marker`, the marker sheet at the origin
    (its mesh `marker` and material must be in the spec)."""
    world.add_geom(
        name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[3, 3, 0.05], pos=[0, 0, -0.75], material="floor"
    )
    hx, hy = TABLE_HALF_EXTENTS_M
    world.add_geom(
        name="table",
        type=mujoco.mjtGeom.mjGEOM_BOX,
        size=[hx, hy, TABLE_THICKNESS_M / 2],
        pos=[0, 0, -TABLE_THICKNESS_M / 2],
        rgba=[0.35, 0.22, 0.12, 1],
    )
    world.add_geom(
        name="table_top",
        type=mujoco.mjtGeom.mjGEOM_PLANE,
        size=[hx, hy, 0.01],
        pos=[0, 0, 1e-5],
        material=top_material,
        contype=0,
        conaffinity=0,
    )
    if marker:
        world.add_geom(
            name="marker",
            type=mujoco.mjtGeom.mjGEOM_MESH,
            meshname="marker",
            material="marker",
            contype=0,
            conaffinity=0,
            pos=[0, 0, 0],
        )


def camera_quat_wxyz(world_from_cam: np.ndarray) -> np.ndarray:
    """Quaternion of a MuJoCo camera (looks along its -z, y up) whose pose is `world_from_cam` (4x4 or 3x3, OpenCV
    axes: the same axes with y and z flipped)."""
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, (world_from_cam[:3, :3] @ np.diag([1.0, -1.0, -1.0])).flatten())
    return quat


def look_at_quat_wxyz(eye_m: np.ndarray, target_m: np.ndarray) -> np.ndarray:
    """Quaternion of a MuJoCo camera (looks along its -z, y up) at eye_m looking at target_m, world z up."""
    opencv_axes = look_at_world_from_cam(eye_m, target_m)[:3, :3]  # x right, y down, z forward
    world_from_cam = opencv_axes * np.array([1.0, -1.0, -1.0])  # MuJoCo's: y up, looking along -z
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, world_from_cam.flatten())
    return quat


def intrinsics_from_fovy(fovy_deg: float, width_px: int, height_px: int) -> dict[str, float]:
    """Pinhole intrinsics of a MuJoCo camera; COLMAP convention: the upper-left pixel's centre is (0.5, 0.5)."""
    fy = 0.5 * height_px / np.tan(np.deg2rad(fovy_deg) / 2)
    return {
        "fx": fy,
        "fy": fy,
        "cx": width_px / 2,
        "cy": height_px / 2,
        "width": width_px,
        "height": height_px,
    }


def world_from_cam_opencv(data: mujoco.MjData, cam_id: int) -> np.ndarray:
    """4x4 camera-to-world pose with OpenCV/COLMAP camera axes (x right, y down, z forward)."""
    pose = np.eye(4)
    pose[:3, :3] = data.cam_xmat[cam_id].reshape(3, 3) @ np.diag([1.0, -1.0, -1.0])
    pose[:3, 3] = data.cam_xpos[cam_id]
    return pose


def write_json(path: Path, payload: object) -> None:
    path.write_text(json.dumps(payload, indent=1) + "\n")


def render_states(
    model: mujoco.MjModel,
    qpos: np.ndarray,
    camera: str,
    height_px: int,
    width_px: int,
    world_from_cam: np.ndarray | None = None,
) -> list[np.ndarray]:
    """(H, W, 3) uint8 frames of `model` seen from `camera` at each row of qpos (T, nq), with progress.

    `world_from_cam` (T, 4, 4), OpenCV axes: move the camera (a child of the world body) to that pose in each frame
    (a moving camera); the camera MuJoCo then renders from is checked against it."""
    data = mujoco.MjData(model)
    cam_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera)
    renderer = mujoco.Renderer(model, height_px, width_px)
    frames = []
    try:
        for k, row in enumerate(qpos):
            if world_from_cam is not None:
                model.cam_pos[cam_id] = world_from_cam[k, :3, 3]
                model.cam_quat[cam_id] = camera_quat_wxyz(world_from_cam[k])
            data.qpos[:] = row
            mujoco.mj_forward(model, data)
            if world_from_cam is not None and not np.allclose(
                world_from_cam_opencv(data, cam_id), world_from_cam[k], atol=1e-9
            ):
                raise RuntimeError(f"frame {k}: the rendered camera is not the planned one")
            renderer.update_scene(data, camera=cam_id)
            frames.append(renderer.render()[:, :, :3].copy())
            print(f"\rrendered {k + 1}/{len(qpos)}", end="", flush=True)
    finally:
        renderer.close()
    print()
    return frames


@contextmanager
def toss_variant(dest: Path, toss_truth: Path, frames: list[np.ndarray], fps: float) -> Iterator[Path]:
    """Stages a variant of the toss sample (same motion, another picture): its video and copies of the toss's
    trajectory, objects and camera; yields the staged `truth/` for the variant's own files, then moves the whole
    folder to `dest` (the old one goes only once the new one is complete)."""
    with tempfile.TemporaryDirectory(dir=dest.parent if dest.parent.exists() else None) as tmp:
        out = Path(tmp) / dest.name
        truth = out / "truth"
        truth.mkdir(parents=True)
        encode_video(frames, out / "video.mp4", fps)
        for name in ("trajectory.npz", "objects.json", "camera.json"):
            shutil.copy2(toss_truth / name, truth / name)
        yield truth
        move_into_place(out, dest)


def move_into_place(built: Path, dest: Path) -> None:
    """Replaces `dest` by the finished sample folder `built` (the old one goes only once the new one is complete)."""
    if dest.exists():
        shutil.rmtree(dest)
    shutil.move(str(built), dest)
    print(f"wrote {dest}")


def encode_video(frames: list[np.ndarray], path: Path, fps: float) -> None:
    """H.264 at high quality (CRF 14) through imageio-ffmpeg's bundled ffmpeg: small files, few artefacts."""
    import imageio_ffmpeg

    height, width = frames[0].shape[:2]
    writer = imageio_ffmpeg.write_frames(
        str(path),
        (width, height),
        fps=fps,
        codec="libx264",
        quality=None,
        output_params=["-crf", "14", "-preset", "slow"],
        pix_fmt_out="yuv420p",
        macro_block_size=1,
    )
    writer.send(None)
    for frame in frames:
        writer.send(np.ascontiguousarray(frame))
    writer.close()


# ---------------------------------------------------------------- markers stuck on objects

# Printed ArUco markers (DICT_4X4_50; the table's is id 0) on the top faces of the box and the can, as they lie:
# marker +y along the body +y, white border one cell wide (1/6 of the black square). The bowl carries none.
OBJECT_MARKERS = (
    {"object": "box", "id": 1, "size_m": 0.048, "margin_m": 0.008},
    {"object": "can", "id": 2, "size_m": 0.036, "margin_m": 0.006},
)
OBJECT_MARKER_PIXELS_PER_M = 4800.0  # the 6 cells of a 4x4 marker land on whole texture pixels for 4.8 and 3.6 cm
OBJECT_MARKER_THICKNESS_M = 0.0003


def add_object_markers(
    spec: mujoco.MjSpec, assets_dir: Path, objects: list[SampleObject], *, absolute_paths: bool = False
) -> list[dict[str, object]]:
    """Adds `OBJECT_MARKERS` to a scene spec as thin textured sheets without contacts or mass (the objects move
    exactly as without them); writes their textures and meshes to assets_dir. Returns the layout: per marker its
    object, id, side of the black square and the marker frame in the object's body frame (origin at the square's
    centre, x along its top edge, y up the marker image, z out of the face).

    Args:
        absolute_paths: refer to the files by absolute path (a spec loaded from another folder's scene.xml).
    """
    by_name = {o.name: o for o in objects}
    layout: list[dict[str, object]] = []
    for row in OBJECT_MARKERS:
        name, marker_id = str(row["object"]), int(row["id"])
        size_m, margin_m = float(row["size_m"]), float(row["margin_m"])
        stem = f"object_marker_{marker_id}"
        texture = marker_texture(OBJECT_MARKER_PIXELS_PER_M, marker_id=marker_id, size_m=size_m, margin_m=margin_m)
        assets_dir.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(assets_dir / f"{stem}.png"), texture)
        write_marker_mesh(assets_dir / f"{stem}.obj", size_m, margin_m, OBJECT_MARKER_THICKNESS_M)
        ref = str(assets_dir.resolve()) + "/" if absolute_paths else ""
        spec.add_texture(name=stem, type=mujoco.mjtTexture.mjTEXTURE_2D, file=f"{ref}{stem}.png")
        material = spec.add_material(name=stem, specular=0.1)
        material.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = stem
        spec.add_mesh(name=stem, file=f"{ref}{stem}.obj")
        top_z_m = float(by_name[name].mesh.extents[2]) / 2.0
        spec.body(name).add_geom(
            name=stem,
            type=mujoco.mjtGeom.mjGEOM_MESH,
            meshname=stem,
            material=stem,
            pos=[0.0, 0.0, top_z_m],
            contype=0,
            conaffinity=0,
            density=0.0,
        )
        # MuJoCo centres a mesh on its centroid: the sheet spans top_z -+ thickness / 2; the printed face is on top.
        face_z_m = top_z_m + OBJECT_MARKER_THICKNESS_M / 2
        layout.append(
            {
                "object": name,
                "id": marker_id,
                "size_m": size_m,
                "pos_m": [0.0, 0.0, round(face_z_m, 9)],
                "quat_wxyz": [1.0, 0.0, 0.0, 0.0],
            }
        )
    return layout
