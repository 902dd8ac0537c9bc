"""Renders a family of tabletop scenes with truth, drawn at random, for grounding on scenes nobody tuned for.

Run: `MUJOCO_GL=osmesa .venv/bin/python samples/make_scene_family.py --seed S --count N OUT`
writes `OUT/scene_<seed>/` for seeds S .. S+N-1; scene k is a pure function of its seed, so any one can be
regenerated alone. `--small` draws the cheap scenes the default tests ground (640x480 video, 1-3 objects).

Seed ranges (keep them apart, so that figures are measured on scenes no test or tuning has seen):
- 0-99: development and tuning;
- 100-199: the default tests (`tests/samples/test_make_scene_family.py`);
- 1000-1999: `benchmarks/scene_family.py` (held out);
- 2000 and up: `benchmarks/speed.py` (its side-by-side inputs: held out from tests and tuning too).

Each scene draws 1-6 objects from these classes (`_family_shapes.py`): boxes (cubes, flat book-like, 3 cm small
ones, cartons), cans and tall thin cylinders, necked bottles, bowls, plates (under 2 cm high), cups and mugs with
and without a handle (walls 3-6 mm), balls (resting on a point) and irregular unions of primitives (toy car,
figure, L-block, box with a knob); some touch. Surfaces are textured or low-texture; the table is one of several
textures; a key light casts hard shadows from a random direction. The capture is either a video (640x480, 960x540
or 1280x720; full orbit, half orbit of about 170 deg, hand-held wobble, high or low pass) or an unordered photo set
(20-40 stills in random order, 1536x1024 or 1200x900). Scale comes from an ArUco marker on the table or from the
largest object's known extent.

Per scene: `video.mp4` or `photos/`, and `truth/`: `scene.xml` + `assets/` (the true MuJoCo scene), `cameras.json`
(intrinsics; per frame or photo `world_from_cam`, OpenCV axes), `objects.json` (as `make_tabletop.py` writes it,
plus each object's class, variant, Euler number and whether it is an open container) and `family.json` (what was
drawn, and the `ground` arguments a user would pass: `--aruco-size 0.12` or `--known-extent <m>`).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "osmesa")

import cv2
import mujoco
import numpy as np
import trimesh

sys.path.insert(0, str(Path(__file__).parent))
import _family_shapes as shapes
import _sample_assets as sa

VIDEO_SIZES_PX = ((640, 480), (960, 540), (1280, 720))
PHOTO_SIZES_PX = ((1536, 1024), (1200, 900))
CAMERA_PATHS = ("full_orbit", "half_orbit", "hand_held", "high_pass", "low_pass")
TABLE_TEXTURES = ("oak", "walnut", "laminate", "fabric", "marble", "cork")
FPS = 10.0
MARKER_KEEP_OUT_M = 0.1  # objects stay clear of the marker sheet (0.16 m square at the origin)
PLACE_RADIUS_M = 0.23


@dataclass(frozen=True, kw_only=True)
class Placed:
    name: str
    shape: shapes.Shape
    mesh: trimesh.Trimesh  # centred on its bounding box (the object frame)
    pos_m: tuple[float, float, float]
    yaw_deg: float
    texture: str
    low_texture: bool
    material: str
    density_kg_m3: float
    friction: tuple[float, float, float]


# ---------------------------------------------------------------- textures


def table_texture(kind: str, rng: np.random.Generator, size: int = 1024) -> np.ndarray:
    """A table top (BGR uint8): woods, speckled laminate, woven fabric, veined marble or cork."""
    if kind in ("oak", "walnut"):
        img = sa.wood_texture(rng, size).astype(np.float32)
        if kind == "walnut":
            img *= np.array([0.55, 0.6, 0.7], np.float32)
        return np.clip(img, 0, 255).astype(np.uint8)
    blobs = sa._blob_noise(rng, size, (1.0, 2.5, 7.0))
    if kind == "laminate":
        base = rng.uniform(150, 210) * np.ones(3, np.float32) + rng.uniform(-20, 20, 3)
        img = base[None, None] * (0.75 + 0.45 * blobs[..., None])
        dots = rng.random((size, size)) < 0.02
        img[dots] *= 0.45
    elif kind == "fabric":
        y, x = np.mgrid[0:size, 0:size].astype(np.float32)
        period = rng.uniform(10, 18)
        weave = 0.5 + 0.25 * np.sin(2 * np.pi * x / period) * np.sign(np.sin(2 * np.pi * y / period))
        base = np.array(rng.uniform(60, 200, 3), np.float32)
        img = base[None, None] * (0.55 + 0.5 * weave[..., None] + 0.35 * (blobs[..., None] - 0.5))
    elif kind == "marble":
        warp = sa._blob_noise(rng, size, (30.0, 80.0))
        y, x = np.mgrid[0:size, 0:size].astype(np.float32) / size
        veins = np.abs(np.sin(2 * np.pi * (3 * x + 2 * y + 2.5 * warp))) ** 0.25
        img = np.full((size, size, 3), 225, np.float32) * (0.55 + 0.45 * veins[..., None])
        img *= (0.9 + 0.2 * blobs)[..., None]
    else:  # cork
        grains = sa._blob_noise(rng, size, (0.8, 1.6, 3.0))
        img = np.array([70, 120, 170], np.float32)[None, None] * (0.55 + 0.7 * grains[..., None])
    return np.clip(img, 0, 255).astype(np.uint8)


def object_texture(material: str, low_texture: bool, rng: np.random.Generator, size: int = 512) -> np.ndarray:
    """An object's surface (BGR uint8): printed cardboard, a tin label, glaze, painted plastic; or, when
    `low_texture`, one matt colour with faint mottling (what makes a white mug hard to reconstruct)."""
    if low_texture:
        colour = rng.uniform(40, 230, 3).astype(np.float32)
        mottle = sa._blob_noise(rng, size, (8.0, 30.0))
        return np.clip(colour[None, None] * (0.95 + 0.1 * mottle[..., None]), 0, 255).astype(np.uint8)
    if material == "cardboard":
        return sa.cardboard_texture(rng, size)
    if material == "metal":
        return sa.label_texture(rng, size)
    if material == "ceramic":
        return sa.ceramic_texture(rng, size)
    base = rng.uniform(40, 230, 3).astype(np.float32)
    img = np.clip(base[None, None] * (0.8 + 0.35 * sa._blob_noise(rng, size, (2.0, 9.0))[..., None]), 0, 255)
    img = img.astype(np.uint8)
    sa._scribble(img, rng, 35, [tuple(int(v) for v in rng.integers(0, 255, 3)) for _ in range(3)])
    return img


MATERIAL_BY_CLASS = {
    "box": ("cardboard", 200.0, 0.55),
    "can": ("metal", 900.0, 0.35),
    "bottle": ("plastic", 500.0, 0.4),
    "bowl": ("ceramic", 2300.0, 0.45),
    "plate": ("ceramic", 2300.0, 0.45),
    "cup": ("ceramic", 2300.0, 0.45),
    "mug": ("ceramic", 2300.0, 0.45),
    "ball": ("plastic", 300.0, 0.6),
    "irregular": ("plastic", 700.0, 0.5),
}


# ---------------------------------------------------------------- drawing a scene


def draw_objects(rng: np.random.Generator, count: int, marker: bool) -> list[Placed]:
    """`count` objects of random classes placed without overlap on the table; about a third touch another."""
    placed: list[Placed] = []
    classes = list(shapes.BUILDERS)
    attempts = 0
    while len(placed) < count and attempts < 400:
        attempts += 1
        object_class = classes[int(rng.integers(len(classes)))]
        shape = shapes.BUILDERS[object_class](rng)
        mesh = sa.centred(shape.mesh)
        footprint_r = float(np.linalg.norm(mesh.extents[:2]) / 2)
        for _ in range(60):
            if placed and rng.random() < 0.35:
                other = placed[int(rng.integers(len(placed)))]
                other_r = float(np.linalg.norm(other.mesh.extents[:2]) / 2)
                direction = rng.uniform(0, 2 * np.pi)
                gap = footprint_r + other_r + 0.001
                xy = np.array(other.pos_m[:2]) + gap * np.array([np.cos(direction), np.sin(direction)])
            else:
                radius = PLACE_RADIUS_M * np.sqrt(rng.random())
                angle = rng.uniform(0, 2 * np.pi)
                xy = radius * np.array([np.cos(angle), np.sin(angle)])
            if np.linalg.norm(xy) + footprint_r > PLACE_RADIUS_M + 0.08:
                continue
            if marker and np.all(np.abs(xy) < MARKER_KEEP_OUT_M + footprint_r * 0.8):
                continue
            clear = all(
                np.linalg.norm(xy - np.array(p.pos_m[:2]))
                >= footprint_r + float(np.linalg.norm(p.mesh.extents[:2]) / 2) + 0.0005
                for p in placed
            )
            if clear:
                break
        else:
            continue
        material, density, friction = MATERIAL_BY_CLASS[object_class]
        low_texture = bool(rng.random() < 0.3)
        name = f"{object_class}_{len(placed)}"
        placed.append(
            Placed(
                name=name,
                shape=shape,
                mesh=mesh,
                pos_m=(float(xy[0]), float(xy[1]), float(mesh.extents[2] / 2)),
                yaw_deg=float(rng.uniform(-180, 180)),
                texture=f"{name}.png",
                low_texture=low_texture,
                material=material,
                density_kg_m3=density,
                friction=(friction, 0.005, 0.0001),
            )
        )
    return placed


def build_spec(
    assets: Path,
    objects: list[Placed],
    *,
    marker: bool,
    light_dir: np.ndarray,
    ambient: float,
    size_px: tuple[int, int],
) -> mujoco.MjSpec:
    """The true scene: floor, table (top at z = 0), optional marker sheet, welded objects, a shadow-casting key
    light from `light_dir`, a fill light and one movable camera."""
    spec = mujoco.MjSpec()
    spec.modelname = "image2sim_family"
    spec.modelfiledir = str(assets.parent)
    spec.meshdir = assets.name
    spec.texturedir = assets.name
    spec.visual.global_.offwidth = max(size_px[0], 640)
    spec.visual.global_.offheight = max(size_px[1], 480)
    spec.visual.quality.shadowsize = 4096
    spec.visual.headlight.ambient = [ambient] * 3
    spec.visual.headlight.diffuse = [0.3, 0.3, 0.3]
    for name in ("table", "floor", "marker") if marker else ("table", "floor"):
        spec.add_texture(name=name, type=mujoco.mjtTexture.mjTEXTURE_2D, file=f"{name}.png")
        mat = spec.add_material(name=name, texrepeat=(3, 3) if name == "floor" else (1, 1), specular=0.2)
        mat.texuniform = name == "floor"
        mat.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = name
    for obj in objects:
        spec.add_texture(name=obj.name, type=mujoco.mjtTexture.mjTEXTURE_CUBE, file=obj.texture)
        mat = spec.add_material(name=obj.name, specular=0.4 if obj.material in ("metal", "ceramic") else 0.1)
        mat.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = obj.name
        spec.add_mesh(name=obj.name, file=f"{obj.name}.obj", inertia=mujoco.mjtMeshInertia.mjMESH_INERTIA_EXACT)
    world = spec.worldbody
    key_pos = -1.7 * light_dir
    world.add_light(name="key", pos=key_pos.tolist(), dir=light_dir.tolist(), diffuse=[0.65] * 3, castshadow=True)
    world.add_light(name="fill", pos=[-0.8, 0.6, 1.4], dir=[0.5, -0.3, -1.0], diffuse=[0.25] * 3, castshadow=False)
    if marker:
        spec.add_mesh(name="marker", file="marker.obj")
    sa.add_floor_and_table(world, top_material="table", marker=marker)
    for obj in objects:
        body = world.add_body(name=obj.name, pos=list(obj.pos_m), quat=sa.yaw_quat_wxyz(obj.yaw_deg).tolist())
        body.add_geom(
            name=f"{obj.name}_geom",
            type=mujoco.mjtGeom.mjGEOM_MESH,
            meshname=obj.name,
            material=obj.name,
            density=obj.density_kg_m3,
            friction=list(obj.friction),
            condim=6,
        )
    world.add_camera(name="video", pos=[0, -0.6, 0.45], fovy=50.0)
    return spec


def video_path(rng: np.random.Generator, kind: str, num_frames: int) -> tuple[np.ndarray, np.ndarray]:
    """(T, 3) camera centres and (T, 3) look-at points of one capture path, world frame (metres)."""
    t = np.arange(num_frames) / num_frames
    start = rng.uniform(0, 2 * np.pi)
    radius = rng.uniform(0.55, 0.72)
    height = rng.uniform(0.33, 0.48)
    span = 2 * np.pi * (num_frames + 1.5) / num_frames  # a little more than a turn: loop closure
    if kind == "half_orbit":
        span = np.deg2rad(rng.uniform(165, 178))
    elif kind == "high_pass":
        radius, height = rng.uniform(0.35, 0.48), rng.uniform(0.6, 0.72)
    elif kind == "low_pass":
        radius, height = rng.uniform(0.6, 0.72), rng.uniform(0.17, 0.24)
    azimuth = start + span * t
    radii = radius + 0.04 * np.sin(2 * 2 * np.pi * t + rng.uniform(0, 6))
    heights = height + 0.04 * np.sin(3 * 2 * np.pi * t + rng.uniform(0, 6))
    eyes = np.stack([radii * np.cos(azimuth), radii * np.sin(azimuth), heights], axis=1)
    targets = np.stack([0.03 * np.sin(2 * np.pi * t), 0.03 * np.cos(4 * np.pi * t), np.full_like(t, 0.02)], axis=1)
    if kind == "hand_held":
        # Smoothed random shake, as a hand gives: about 1.5 cm of position, 2 cm of aim.
        for arr, amplitude in ((eyes, 0.015), (targets, 0.02)):
            shake = rng.standard_normal((num_frames + 8, 3))
            kernel = np.hanning(7)
            shake = np.stack([np.convolve(shake[:, k], kernel / kernel.sum(), "same") for k in range(3)], 1)[4:-4]
            arr += amplitude * shake / (shake.std(axis=0) + 1e-9)
    return eyes, targets


def photo_poses(rng: np.random.Generator, count: int) -> tuple[np.ndarray, np.ndarray]:
    """Stills from anywhere around the table: random azimuth, 20-60 deg elevation, 0.4-0.75 m away."""
    azimuth = rng.uniform(0, 2 * np.pi, count)
    elevation = np.deg2rad(rng.uniform(20, 60, count))
    distance = rng.uniform(0.42, 0.75, count)
    eyes = np.stack(
        [
            distance * np.cos(elevation) * np.cos(azimuth),
            distance * np.cos(elevation) * np.sin(azimuth),
            distance * np.sin(elevation),
        ],
        axis=1,
    )
    targets = np.concatenate([rng.uniform(-0.06, 0.06, (count, 2)), rng.uniform(0.0, 0.04, (count, 1))], axis=1)
    return eyes, targets


def euler_merged(mesh: trimesh.Trimesh) -> int:
    merged = mesh.copy()
    merged.merge_vertices()
    return int(merged.euler_number)


def make_scene(seed: int, out: Path, *, small: bool) -> dict[str, object]:
    """Draws and renders scene `seed` into `out` (which must not exist); returns its `family.json` record."""
    rng = np.random.default_rng(seed)
    photos = (not small) and rng.random() < 0.25
    marker = bool(rng.random() < 0.6)
    count = int(rng.integers(1, 4)) if small else int(rng.integers(1, 7))
    objects = draw_objects(rng, count, marker)
    table_kind = TABLE_TEXTURES[int(rng.integers(len(TABLE_TEXTURES)))]
    if photos:
        size_px = PHOTO_SIZES_PX[int(rng.integers(len(PHOTO_SIZES_PX)))]
        num_views = int(rng.integers(20, 41))
        path_kind = "unordered_photos"
        eyes, targets = photo_poses(rng, num_views)
        fovy_deg = float(rng.uniform(45, 55))
    else:
        size_px = (640, 480) if small else VIDEO_SIZES_PX[int(rng.integers(len(VIDEO_SIZES_PX)))]
        num_views = int(rng.integers(44, 52)) if small else int(rng.integers(56, 81))
        path_kind = CAMERA_PATHS[int(rng.integers(len(CAMERA_PATHS)))]
        eyes, targets = video_path(rng, path_kind, num_views)
        fovy_deg = float(rng.uniform(45, 55) if size_px[0] / size_px[1] < 1.5 else rng.uniform(38, 45))
    light_azimuth, light_elevation = rng.uniform(0, 2 * np.pi), np.deg2rad(rng.uniform(35, 70))
    light_dir = -np.array(
        [
            np.cos(light_elevation) * np.cos(light_azimuth),
            np.cos(light_elevation) * np.sin(light_azimuth),
            np.sin(light_elevation),
        ]
    )
    ambient = float(rng.uniform(0.15, 0.3))

    truth = out / "truth"
    assets = truth / "assets"
    assets.mkdir(parents=True)
    cv2.imwrite(str(assets / "table.png"), table_texture(table_kind, rng))
    cv2.imwrite(str(assets / "floor.png"), sa.floor_texture(rng))
    if marker:
        cv2.imwrite(str(assets / "marker.png"), sa.marker_texture())
        sa.write_marker_mesh(assets / "marker.obj")
    for obj in objects:
        cv2.imwrite(str(assets / obj.texture), object_texture(obj.material, obj.low_texture, rng))
        obj.mesh.export(assets / f"{obj.name}.obj")
    spec = build_spec(assets, objects, marker=marker, light_dir=light_dir, ambient=ambient, size_px=size_px)
    (truth / "scene.xml").write_text(spec.to_xml())
    model = spec.compile()
    data = mujoco.MjData(model)
    cam_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, "video")
    model.cam_fovy[cam_id] = fovy_deg
    width, height = size_px
    renderer = mujoco.Renderer(model, height, width)
    frames, poses = [], []
    try:
        for k in range(num_views):
            model.cam_pos[cam_id] = eyes[k]
            model.cam_quat[cam_id] = sa.look_at_quat_wxyz(eyes[k], targets[k])
            mujoco.mj_forward(model, data)
            renderer.update_scene(data, camera=cam_id)
            frames.append(renderer.render()[:, :, :3].copy())
            poses.append(sa.world_from_cam_opencv(data, cam_id))
            print(f"\rscene {seed}: rendered {k + 1}/{num_views}", end="", flush=True)
    finally:
        renderer.close()
    print()
    frame_records = [{"frame_index": k, "world_from_cam": pose.round(9).tolist()} for k, pose in enumerate(poses)]
    if photos:
        (out / "photos").mkdir()
        # Random file names: sorted by name, the photos come in no order a video would have.
        numbers = rng.choice(np.arange(1000, 9999), size=num_views, replace=False)
        names = [f"IMG_{n}.jpg" for n in numbers]
        for name, frame, record in zip(names, frames, frame_records, strict=True):
            cv2.imwrite(
                str(out / "photos" / name), cv2.cvtColor(frame, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 92]
            )
            record["image_name"] = name
        order = np.argsort(names)
        for index, k in enumerate(order):
            frame_records[k]["frame_index"] = int(index)  # the index `ground` gives it: its place in the sorted folder
        source = "photos"
    else:
        sa.encode_video(frames, out / "video.mp4", FPS)
        source = "video.mp4"
    largest = max(objects, key=lambda o: float(o.mesh.extents.max()))
    known_extent_m = round(float(largest.mesh.extents.max()), 4)
    ground_args = ["--aruco-size", str(sa.MARKER_SIZE_M)] if marker else ["--known-extent", str(known_extent_m)]
    sa.write_json(
        truth / "cameras.json",
        {
            "convention": "world = table frame (the ArUco marker's when there is one: x right, y top, z up; table "
            "top z=0); world_from_cam maps OpenCV camera coordinates (x right, y down, z forward) to world, metres",
            "intrinsics": sa.intrinsics_from_fovy(fovy_deg, width, height),
            "fovy_deg": fovy_deg,
            "fps": FPS if not photos else None,
            "frames": frame_records,
        },
    )
    sa.write_json(
        truth / "objects.json",
        {
            "convention": "object frame = mesh bounding-box centre; world_from_object = (pos_m, quat_wxyz)",
            "table": {"top_z_m": 0.0, "half_extents_m": list(sa.TABLE_HALF_EXTENTS_M)},
            "objects": [
                {
                    "name": obj.name,
                    "class": obj.shape.object_class,
                    "variant": obj.shape.variant,
                    "mesh": f"assets/{obj.name}.obj",
                    "pos_m": list(obj.pos_m),
                    "quat_wxyz": sa.yaw_quat_wxyz(obj.yaw_deg).tolist(),
                    "extents_m": obj.mesh.extents.round(9).tolist(),
                    "volume_m3": float(obj.mesh.volume),
                    "euler_number": euler_merged(obj.mesh),
                    "open_container": obj.shape.object_class in shapes.OPEN_CONTAINERS,
                    "low_texture": obj.low_texture,
                    "material": obj.material,
                    "density_kg_m3": obj.density_kg_m3,
                    "mass_kg": float(obj.mesh.volume * obj.density_kg_m3),
                    "friction": list(obj.friction),
                }
                for obj in objects
            ],
        },
    )
    record = {
        "seed": seed,
        "source": source,
        "ground_args": ground_args,
        "capture": path_kind,
        "views": num_views,
        "size_px": list(size_px),
        "scale_by": "marker" if marker else "known_extent",
        "table_texture": table_kind,
        "objects": [
            f"{o.shape.object_class}/{o.shape.variant}{' (low texture)' if o.low_texture else ''}" for o in objects
        ],
    }
    sa.write_json(truth / "family.json", record)
    return record


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path, help="folder to write scene_<seed>/ folders into (created)")
    parser.add_argument("--seed", type=int, required=True, help="first seed (see the seed ranges above)")
    parser.add_argument("--count", type=int, default=1, help="number of scenes")
    parser.add_argument("--small", action="store_true", help="cheap scenes: 640x480 video, 1-3 objects")
    parser.add_argument("--overwrite", action="store_true", help="re-render scenes that already exist")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    for seed in range(args.seed, args.seed + args.count):
        dest = args.out / f"scene_{seed:05d}"
        if dest.exists() and not args.overwrite:
            print(f"{dest} exists; kept (--overwrite re-renders it)")
            continue
        with tempfile.TemporaryDirectory(dir=args.out) as tmp:
            built = Path(tmp) / dest.name
            record = make_scene(seed, built, small=args.small)
            sa.move_into_place(built, dest)
        print(
            f"  {record['capture']}, {record['size_px'][0]}x{record['size_px'][1]}, {record['scale_by']}, "
            f"{record['table_texture']} table: {', '.join(record['objects'])}"
        )


if __name__ == "__main__":
    main()
