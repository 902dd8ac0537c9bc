"""Synthetic training data for the property model, rendered with MuJoCo.

One "studio" model holds a pool of procedural shapes (boxes, cylinders, ellipsoids, capsules, bowls, cups, bottles;
some lying on their side) and a bank of procedural textures per material (wood grain, brushed metal, printed can
labels, moulded plastic, matte rubber, transparent glass, glossy speckled ceramic, printed cardboard, porous foam,
woven fabric). Each sample picks a material from the table (`_properties_materials`), a shape the material usually
comes in, a texture of that material with a random tint and the material's gloss, a random table top, lights and
three camera views, then crops the object exactly as `ground` crops it from a video (`crop_object`).

Held-out data comes from other seeds: another shape pool, another texture bank, other lights and cameras.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

from grounder.errors import GrounderError, integer_in
from grounder.properties.materials import MATERIAL_NAMES, MATERIALS, Material, sample_properties
from image2sim_common.progress import ProgressFn
from image2sim_common.rotations import look_at_world_from_cam

CROP_PX = 64
NUM_VIEWS = 3
NUM_SHAPE_FEATURES = 8
_RENDER_PX = 96
_TEX_PX = 64
_TEXTURES_PER_MATERIAL = 48
_MESHES_PER_KIND = 10
_HIDDEN_GROUP = 5
MAX_SAMPLES = 100_000
"""Most objects one `generate_dataset` call renders: their crops alone are allocated up front, 36,864 bytes each
(3 views x 64 x 64 x RGB uint8), so 100,000 take 3.7 GB (and ~30 min to render at ~18 ms each on one core)."""

# Sizes of training and evaluation runs, here (no torch) so that the CLI refuses a bad one at once.
MIN_NUM_TRAIN = 100
MAX_NUM_TRAIN = 50_000
"""Training holds every crop twice, as rendered (uint8, 37 KB an object) and as the float32 tensor it trains on
(147 KB): 50,000 objects take ~9 GB, 3.5 times the default's 14,000 (and ~50 s an epoch on 2 cores)."""
MAX_EPOCHS = 1000
"""An epoch takes ~1 s per 1,000 objects on 2 cores: 1000 epochs of the default 14,000 are ~4 h (the recipe's 30
take 7 min); more is a run that looks stuck."""
MIN_EVAL_SAMPLES = 10


@dataclass(frozen=True, kw_only=True)
class PropertyDataset:
    """Rendered samples with their true properties.

    Attributes:
        crops: (N, V, 64, 64, 3) uint8 RGB object crops from V views.
        shape_features: (N, 8) float32, `shape_features` of each object.
        targets: (N, 6) float32 regression targets (`TARGET_NAMES`).
        material: (N,) int64 index into `MATERIAL_NAMES`.
        seed: generator seed.
    """

    crops: np.ndarray
    shape_features: np.ndarray
    targets: np.ndarray
    material: np.ndarray
    seed: int


# ---------------------------------------------------------------- shape features (shared with `ground`)


def shape_features(vertices_m: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Scale and form of a watertight mesh standing on the table (z up), the model's shape input.

    Args:
        vertices_m: (V, 3) vertices, metres, world-aligned axes (z up).
        faces: (F, 3) triangles.

    Returns:
        (8,) float32: ln long and short horizontal extent (minimum-area rectangle), ln height, ln volume,
        fill (volume / that box), convexity (volume / convex-hull volume), ln(area / volume^(2/3)),
        ln thickness (2 volume / area).
    """
    import cv2
    import trimesh

    mesh = trimesh.Trimesh(vertices=np.asarray(vertices_m, dtype=np.float64), faces=np.asarray(faces), process=False)
    volume = abs(float(mesh.volume))
    area = float(mesh.area)
    hull_volume = float(mesh.convex_hull.volume)
    (_, _), (w, h), _ = cv2.minAreaRect(np.asarray(mesh.vertices[:, :2], dtype=np.float32))
    long_m, short_m = max(w, h, 1e-4), max(min(w, h), 1e-4)
    height_m = max(float(np.ptp(mesh.vertices[:, 2])), 1e-4)
    volume = max(volume, 1e-9)
    return np.array(
        [
            math.log(long_m),
            math.log(short_m),
            math.log(height_m),
            math.log(volume),
            min(volume / (long_m * short_m * height_m), 1.5),
            min(volume / max(hull_volume, 1e-12), 1.5),
            math.log(area / volume ** (2 / 3)),
            math.log(2 * volume / area),
        ],
        dtype=np.float32,
    )


# ---------------------------------------------------------------- crops (shared with `ground`)


def project_points(points_world: np.ndarray, world_from_cam: np.ndarray, camera_matrix: np.ndarray) -> np.ndarray:
    """(N, 3) world points -> (N, 3) pixel u, v and depth z (OpenCV camera axes)."""
    cam_from_world = np.linalg.inv(world_from_cam)
    p = points_world @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
    z = p[:, 2]
    uv = (p @ camera_matrix.T)[:, :2] / np.maximum(z[:, None], 1e-9)
    return np.column_stack([uv, z])


def bbox_corners(vertices_world_m: np.ndarray) -> np.ndarray:
    """(8, 3) corners of the axis-aligned box around the points."""
    lo, hi = vertices_world_m.min(axis=0), vertices_world_m.max(axis=0)
    return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])


def crop_box_px(corners_uvz: np.ndarray, margin: float = 1.15) -> tuple[float, float, float]:
    """Square crop (centre u, centre v, side) around projected corners; the same rule in training and `ground`."""
    lo, hi = corners_uvz[:, :2].min(axis=0), corners_uvz[:, :2].max(axis=0)
    centre = (lo + hi) / 2
    return float(centre[0]), float(centre[1]), float(max(hi - lo) * margin)


def crop_square(image_rgb: np.ndarray, box: tuple[float, float, float], out_px: int = CROP_PX) -> np.ndarray:
    """The square `box` of the image resized to out_px (area averaging); outside the image is mid-grey."""
    import cv2

    cu, cv, side = box
    side_i = max(2, round(side))
    x0, y0 = round(cu - side_i / 2), round(cv - side_i / 2)
    h, w = image_rgb.shape[:2]
    pad = max(0, -x0, -y0, x0 + side_i - w, y0 + side_i - h)
    padded = image_rgb
    if pad:
        padded = cv2.copyMakeBorder(image_rgb, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=(128, 128, 128))
    patch = padded[y0 + pad : y0 + pad + side_i, x0 + pad : x0 + pad + side_i]
    interpolation = cv2.INTER_AREA if side_i > out_px else cv2.INTER_LINEAR
    return np.ascontiguousarray(cv2.resize(patch, (out_px, out_px), interpolation=interpolation))


# ---------------------------------------------------------------- procedural shapes


def _revolve(profile_rz: list[tuple[float, float]], sections: int = 32) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    mesh = trimesh.creation.revolve(np.asarray(profile_rz, dtype=np.float64), sections=sections)
    if mesh.volume < 0:
        mesh.invert()
    return np.asarray(mesh.vertices), np.asarray(mesh.faces)


def _make_shape(kind: str, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A watertight mesh of roughly unit size (longest extent ~0.1 m), standing on z = 0, centred in x, y."""
    import trimesh

    u = rng.uniform
    if kind == "box":
        mesh = trimesh.creation.box(extents=[0.1, 0.1 * u(0.3, 1.0), 0.1 * u(0.2, 1.2)])
    elif kind == "cylinder":
        mesh = trimesh.creation.cylinder(radius=0.05 * u(0.3, 1.0), height=0.1 * u(0.3, 1.5), sections=32)
    elif kind == "ellipsoid":
        mesh = trimesh.creation.icosphere(subdivisions=3, radius=0.05)
        mesh.apply_scale([1.0, u(0.5, 1.0), u(0.4, 1.0)])
    elif kind == "capsule":
        mesh = trimesh.creation.capsule(height=0.1 * u(0.3, 1.0), radius=0.05 * u(0.3, 0.7), count=[16, 16])
    elif kind == "bowl":
        r, h, t = 0.05, 0.1 * u(0.25, 0.5), 0.1 * u(0.04, 0.1)
        foot = r * u(0.35, 0.6)
        mesh = trimesh.Trimesh(
            *_revolve([(0, 0), (foot, 0), (r, h), (r - t, h), (foot - t * 0.5, t), (0, t)]), process=True
        )
    elif kind == "cup":
        r, h, t = 0.05 * u(0.5, 0.8), 0.1 * u(0.6, 1.1), 0.1 * u(0.03, 0.06)
        mesh = trimesh.Trimesh(*_revolve([(0, 0), (r * 0.9, 0), (r, h), (r - t, h), (r * 0.9 - t, t), (0, t)]))
    elif kind == "bottle":
        r, h = 0.05 * u(0.3, 0.55), 0.1 * u(1.0, 1.5)
        neck = r * u(0.3, 0.5)
        mesh = trimesh.Trimesh(
            *_revolve([(0, 0), (r, 0), (r, h * 0.6), (neck, h * 0.8), (neck, h), (0, h)]), process=True
        )
    else:
        raise ValueError(f"unknown shape kind {kind!r}")
    if kind in ("cylinder", "capsule", "bottle") and rng.random() < 0.3:
        mesh.apply_transform(trimesh.transformations.rotation_matrix(math.pi / 2, [1, 0, 0]))
    mesh.apply_scale(0.1 / float(max(mesh.extents)))
    lo, hi = mesh.bounds
    mesh.apply_translation([-(lo[0] + hi[0]) / 2, -(lo[1] + hi[1]) / 2, -lo[2]])
    return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)


SHAPE_KINDS: tuple[str, ...] = ("box", "cylinder", "ellipsoid", "capsule", "bowl", "cup", "bottle")


# ---------------------------------------------------------------- procedural textures


def _smooth_noise(rng: np.random.Generator, size: int, cells: int) -> np.ndarray:
    import cv2

    coarse = rng.random((cells, cells)).astype(np.float32)
    return np.asarray(cv2.resize(coarse, (size, size), interpolation=cv2.INTER_CUBIC))


def _hsv(h: float, s: float, v: float) -> np.ndarray:
    import colorsys

    return np.array(colorsys.hsv_to_rgb(h % 1.0, s, v), dtype=np.float32)


def _paint_marks(img: np.ndarray, rng: np.random.Generator, count: int, colours: list[np.ndarray]) -> None:
    """Printed rectangles, bars and dots (labels, logos, text blocks)."""
    n = img.shape[0]
    for _ in range(count):
        c = colours[rng.integers(len(colours))]
        x, y = rng.integers(0, n, size=2)
        if rng.random() < 0.5:
            w, h = rng.integers(2, n // 3), rng.integers(1, n // 8)
            img[y : y + h, x : x + w] = c
        else:
            r = rng.integers(1, n // 8)
            yy, xx = np.ogrid[:n, :n]
            img[(yy - y) ** 2 + (xx - x) ** 2 <= r * r] = c


def make_texture(material: str, rng: np.random.Generator, size: int = _TEX_PX) -> np.ndarray:
    """(size, size, 3) uint8 RGB texture whose look follows the material (grain, streaks, print, weave...)."""
    n = size
    yy, xx = np.mgrid[:n, :n].astype(np.float32) / n
    fine = rng.random((n, n)).astype(np.float32)
    if material == "wood":
        base = _hsv(rng.uniform(0.05, 0.11), rng.uniform(0.4, 0.75), rng.uniform(0.35, 0.85))
        warp = _smooth_noise(rng, n, 4) * rng.uniform(1.0, 3.0)
        rings = 0.5 + 0.5 * np.sin(2 * np.pi * (rng.uniform(4, 10) * yy + warp))
        shade = 0.7 + 0.25 * rings + 0.05 * fine
        img = base[None, None] * shade[..., None]
    elif material == "metal":
        grey = rng.uniform(0.45, 0.85)
        tint = _hsv(rng.uniform(0.05, 0.15), rng.uniform(0.0, 0.5) if rng.random() < 0.25 else 0.0, 1.0)
        streaks = np.repeat(rng.random((n, 1)).astype(np.float32), n, axis=1)
        shade = grey * (0.85 + 0.15 * streaks + 0.04 * fine)
        img = tint[None, None] * shade[..., None]
    elif material == "metal_can":
        img = np.empty((n, n, 3), np.float32)
        bands = np.sort(rng.integers(0, n, size=rng.integers(2, 5)))
        colours = [_hsv(rng.random(), rng.uniform(0.5, 1.0), rng.uniform(0.5, 1.0)) for _ in range(len(bands) + 1)]
        edges = [0, *bands.tolist(), n]
        for c, (a, b) in zip(colours, itertools.pairwise(edges), strict=True):
            img[a:b] = c
        white = np.ones(3, np.float32)
        _paint_marks(img, rng, int(rng.integers(8, 25)), [*colours, white, np.zeros(3, np.float32)])
        rim = max(1, n // 16)
        img[:rim] = img[-rim:] = rng.uniform(0.6, 0.8)
    elif material == "plastic":
        base = _hsv(rng.random(), rng.uniform(0.5, 1.0), rng.uniform(0.4, 1.0))
        if rng.random() < 0.2:
            base = np.full(3, rng.uniform(0.1, 0.95), np.float32)
        img = base[None, None] * (0.95 + 0.05 * _smooth_noise(rng, n, 8)[..., None])
    elif material == "rubber":
        if rng.random() < 0.6:
            base = np.full(3, rng.uniform(0.05, 0.3), np.float32)
        else:
            base = _hsv(rng.random(), rng.uniform(0.5, 0.9), rng.uniform(0.3, 0.8))
        img = base[None, None] * (0.8 + 0.2 * fine[..., None])
    elif material == "glass":
        base = _hsv(rng.choice([0.33, 0.55, 0.1, 0.0]), rng.uniform(0.0, 0.5), rng.uniform(0.75, 1.0))
        img = base[None, None] * (0.97 + 0.03 * fine[..., None])
    elif material == "ceramic":
        base = _hsv(rng.random(), rng.uniform(0.0, 0.6), rng.uniform(0.6, 1.0))
        img = np.repeat(base[None, None], n, 0).repeat(n, 1)
        img = img * (0.96 + 0.04 * _smooth_noise(rng, n, 6)[..., None])
        speckle = rng.random((n, n)) < rng.uniform(0.0, 0.05)
        img[speckle] = _hsv(rng.random(), rng.uniform(0.3, 1.0), rng.uniform(0.1, 0.6))
        if rng.random() < 0.4:
            _paint_marks(img, rng, int(rng.integers(2, 10)), [_hsv(rng.random(), 0.8, 0.5)])
    elif material == "cardboard":
        base = _hsv(rng.uniform(0.07, 0.11), rng.uniform(0.35, 0.6), rng.uniform(0.5, 0.8))
        fibres = np.repeat(rng.random((1, n)).astype(np.float32), n, axis=0)
        img = base[None, None] * (0.88 + 0.07 * fibres[..., None] + 0.05 * fine[..., None])
        colours = [_hsv(rng.random(), rng.uniform(0.4, 1.0), rng.uniform(0.2, 0.8)) for _ in range(3)]
        _paint_marks(img, rng, int(rng.integers(0, 20)), [*colours, np.zeros(3, np.float32)])
        if rng.random() < 0.5:
            y = int(rng.integers(0, n - 6))
            img[y : y + n // 10] = _hsv(rng.uniform(0.08, 0.12), 0.3, 0.9)  # tape
    elif material == "foam":
        base = _hsv(rng.random(), rng.uniform(0.0, 0.6), rng.uniform(0.65, 1.0))
        pores = (rng.random((n, n)) < 0.18).astype(np.float32)
        img = base[None, None] * (1.0 - 0.25 * pores[..., None] - 0.08 * fine[..., None])
    elif material == "fabric":
        base = _hsv(rng.random(), rng.uniform(0.3, 0.9), rng.uniform(0.3, 0.9))
        f = rng.choice([8, 12, 16])
        weave = 0.5 + 0.25 * np.sin(2 * np.pi * f * xx) * np.sin(2 * np.pi * f * yy) + 0.25 * fine
        img = base[None, None] * (0.75 + 0.35 * weave[..., None])
        if rng.random() < 0.4:
            stripe = np.sin(2 * np.pi * rng.integers(2, 6) * (xx if rng.random() < 0.5 else yy)) > 0.3
            img[stripe] = _hsv(rng.random(), 0.7, 0.7) * 0.9
    else:
        raise ValueError(f"unknown material {material!r}")
    return np.asarray(np.clip(img * 255, 0, 255), dtype=np.uint8)


@dataclass(frozen=True)
class _Look:
    """Ranges of MuJoCo material parameters per material class (specular, shininess, reflectance, alpha)."""

    specular: tuple[float, float]
    shininess: tuple[float, float]
    reflectance: tuple[float, float]
    alpha: tuple[float, float] = (1.0, 1.0)


_LOOKS = {
    "wood": _Look((0.05, 0.3), (0.1, 0.4), (0.0, 0.05)),
    "metal": _Look((0.7, 1.0), (0.7, 1.0), (0.2, 0.5)),
    "metal_can": _Look((0.5, 0.9), (0.5, 0.9), (0.05, 0.2)),
    "plastic": _Look((0.3, 0.6), (0.3, 0.7), (0.0, 0.1)),
    "rubber": _Look((0.0, 0.08), (0.0, 0.2), (0.0, 0.0)),
    "glass": _Look((0.8, 1.0), (0.8, 1.0), (0.1, 0.3), (0.3, 0.6)),
    "ceramic": _Look((0.6, 1.0), (0.6, 1.0), (0.05, 0.2)),
    "cardboard": _Look((0.0, 0.1), (0.0, 0.2), (0.0, 0.0)),
    "foam": _Look((0.0, 0.05), (0.0, 0.1), (0.0, 0.0)),
    "fabric": _Look((0.0, 0.05), (0.0, 0.1), (0.0, 0.0)),
}


# ---------------------------------------------------------------- the studio


class _Studio:
    """A MuJoCo model with every shape and texture of one seed, re-posed and re-lit per sample; one renderer."""

    def __init__(self, seed: int) -> None:
        import mujoco

        rng = np.random.default_rng([seed, 1])
        self.shapes: list[tuple[str, np.ndarray, np.ndarray]] = [
            (kind, *_make_shape(kind, rng)) for kind in SHAPE_KINDS for _ in range(_MESHES_PER_KIND)
        ]
        spec = mujoco.MjSpec()
        spec.visual.global_.offwidth = _RENDER_PX
        spec.visual.global_.offheight = _RENDER_PX
        spec.visual.quality.shadowsize = 1024
        spec.visual.quality.offsamples = 0
        self.material_ids: dict[str, list[int]] = {}
        mat_count = 0
        for material in MATERIAL_NAMES:
            ids = []
            for k in range(_TEXTURES_PER_MATERIAL):
                name = f"{material}_{k}"
                image = make_texture(material, rng)
                tex = spec.add_texture(
                    name=name, type=mujoco.mjtTexture.mjTEXTURE_CUBE, width=_TEX_PX, height=_TEX_PX * 6, nchannel=3
                )
                tex.data = np.tile(image, (6, 1, 1)).tobytes()
                mat = spec.add_material(name=name)
                mat.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = name
                ids.append(mat_count)
                mat_count += 1
            self.material_ids[material] = ids
        self.table_ids = []
        for k in range(6):
            name = f"table_{k}"
            if k % 2 == 0:
                image = make_texture("wood", rng, size=128)
            else:  # laminate, stone, painted: a neutral colour with fine noise
                grey = rng.uniform(0.3, 0.9) * np.clip(1 + rng.normal(0, 0.06, 3), 0.8, 1.2)
                noise = 0.9 + 0.1 * rng.random((128, 128, 1))
                image = np.asarray(np.clip(grey * noise * 255, 0, 255), dtype=np.uint8)
            tex = spec.add_texture(name=name, type=mujoco.mjtTexture.mjTEXTURE_2D, width=128, height=128, nchannel=3)
            tex.data = image.tobytes()
            mat = spec.add_material(name=name, texrepeat=[4, 4], specular=0.2)
            mat.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = name
            self.table_ids.append(mat_count)
            mat_count += 1
        self.table_geom = spec.worldbody.add_geom(
            name="table", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[3, 3, 0.1], material="table_0"
        )
        for i, (_, vertices, faces) in enumerate(self.shapes):
            spec.add_mesh(name=f"shape_{i}", uservert=vertices.ravel().tolist(), userface=faces.ravel().tolist())
            spec.worldbody.add_geom(
                name=f"shape_{i}",
                type=mujoco.mjtGeom.mjGEOM_MESH,
                meshname=f"shape_{i}",
                material=f"{MATERIAL_NAMES[0]}_0",
                group=_HIDDEN_GROUP,
                contype=0,
                conaffinity=0,
            )
        spec.worldbody.add_light(name="key", pos=[0.5, 0.3, 1.5], dir=[0, 0, -1], castshadow=True)
        spec.worldbody.add_light(name="fill", pos=[-0.5, -0.3, 1.0], dir=[0, 0, -1], castshadow=False)
        spec.worldbody.add_camera(name="view", pos=[0, -0.5, 0.3])
        self.model = spec.compile()
        self.data = mujoco.MjData(self.model)
        self.first_shape_geom = self.model.geom("shape_0").id
        self.renderer = mujoco.Renderer(self.model, _RENDER_PX, _RENDER_PX)
        self.option = mujoco.MjvOption()
        self.option.geomgroup[_HIDDEN_GROUP] = 0

    def close(self) -> None:
        self.renderer.close()

    def render_sample(self, material: Material, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """(V, 64, 64, 3) crops and (8,) shape features of one random object of this material."""
        import mujoco

        m, d = self.model, self.data
        kinds = list(material.shapes)
        weights = np.array([material.shapes[k] for k in kinds])
        kind = kinds[rng.choice(len(kinds), p=weights / weights.sum())]
        choices = [i for i, s in enumerate(self.shapes) if s[0] == kind]
        index = int(rng.choice(choices))
        _, vertices, faces = self.shapes[index]
        geom = self.first_shape_geom + index
        m.geom_group[self.first_shape_geom :] = _HIDDEN_GROUP
        m.geom_group[geom] = 0
        yaw = rng.uniform(0, 2 * math.pi)
        m.geom_quat[geom] = [math.cos(yaw / 2), 0, 0, math.sin(yaw / 2)]
        rotation = np.array([[math.cos(yaw), -math.sin(yaw), 0], [math.sin(yaw), math.cos(yaw), 0], [0, 0, 1]])
        world_vertices = vertices @ rotation.T

        # Appearance: a texture of this material, tinted, with the material's gloss.
        mat = int(rng.choice(self.material_ids[material.name]))
        look = _LOOKS[material.name]
        m.geom_matid[geom] = mat
        tint = np.clip(1.0 + rng.normal(0, 0.08, 3), 0.7, 1.0)
        m.mat_rgba[mat] = [*tint, rng.uniform(*look.alpha)]
        m.mat_specular[mat] = rng.uniform(*look.specular)
        m.mat_shininess[mat] = rng.uniform(*look.shininess)
        m.mat_reflectance[mat] = rng.uniform(*look.reflectance)
        m.geom_matid[self.table_geom.id] = int(rng.choice(self.table_ids))
        table_mat = m.geom_matid[self.table_geom.id]
        m.mat_rgba[table_mat] = [*np.clip(rng.uniform(0.75, 1.0) + rng.normal(0, 0.04, 3), 0, 1), 1.0]

        # Lights.
        m.vis.headlight.ambient[:] = rng.uniform(0.1, 0.35)
        m.vis.headlight.diffuse[:] = rng.uniform(0.2, 0.5)
        for light in range(2):
            az, el, dist = rng.uniform(0, 2 * math.pi), rng.uniform(0.6, 1.4), rng.uniform(0.8, 2.0)
            pos = dist * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
            m.light_pos[light] = pos
            m.light_dir[light] = -pos / np.linalg.norm(pos)
            m.light_diffuse[light] = rng.uniform(0.3, 0.8) * np.clip(1 + rng.normal(0, 0.05, 3), 0.8, 1.1)

        # Views spread around the object, as `ground` picks them from an orbit.
        corners = bbox_corners(world_vertices)
        centre = corners.mean(axis=0)
        radius = float(np.linalg.norm(corners[0] - centre))
        fovy_deg = rng.uniform(40, 60)
        m.cam_fovy[0] = fovy_deg
        focal = 0.5 * _RENDER_PX / math.tan(math.radians(fovy_deg) / 2)
        camera_matrix = np.array([[focal, 0, _RENDER_PX / 2], [0, focal, _RENDER_PX / 2], [0, 0, 1]])
        az0 = rng.uniform(0, 2 * math.pi)
        crops = []
        for view in range(NUM_VIEWS):
            az = az0 + view * 2 * math.pi / NUM_VIEWS + rng.normal(0, 0.3)
            el = rng.uniform(0.25, 1.1)
            fill = rng.uniform(0.55, 0.9)
            dist = radius / math.tan(math.radians(fovy_deg) / 2) / fill
            target = centre + rng.normal(0, 0.05 * radius, 3)
            position = target + dist * np.array(
                [math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)]
            )
            world_from_cam = look_at_world_from_cam(position, target)
            m.cam_pos[0] = position
            quat = np.zeros(4)
            mujoco.mju_mat2Quat(quat, (world_from_cam[:3, :3] @ np.diag([1.0, -1.0, -1.0])).ravel())
            m.cam_quat[0] = quat
            mujoco.mj_kinematics(m, d)
            mujoco.mj_camlight(m, d)
            self.renderer.update_scene(d, camera=0, scene_option=self.option)
            image = self.renderer.render()
            box = crop_box_px(project_points(corners, world_from_cam, camera_matrix))
            crops.append(crop_square(image, box))
        scale = float(np.exp(rng.uniform(math.log(0.4), math.log(3.0))))  # longest extent 4-30 cm
        features = shape_features(world_vertices * scale, faces)
        return np.stack(crops), features


def generate_dataset(num_samples: int, seed: int, *, progress: ProgressFn | None = None) -> PropertyDataset:
    """Renders `num_samples` objects (materials balanced) with their true properties; deterministic per seed.

    Raises:
        GrounderError: `num_samples` is not an integer between 1 and `MAX_SAMPLES` (checked before any allocation).
    """
    if not integer_in(num_samples, 1, MAX_SAMPLES):
        raise GrounderError(
            f"num_samples={num_samples!r} but expected an integer between 1 and {MAX_SAMPLES} "
            "(each object's crops take 37 KB)"
        )
    rng = np.random.default_rng([seed, 2])
    studio = _Studio(seed)
    crops = np.empty((num_samples, NUM_VIEWS, CROP_PX, CROP_PX, 3), np.uint8)
    features = np.empty((num_samples, NUM_SHAPE_FEATURES), np.float32)
    targets = np.empty((num_samples, 6), np.float32)
    material_index = np.empty(num_samples, np.int64)
    try:
        for i in range(num_samples):
            k = i % len(MATERIALS)
            material = MATERIALS[k]
            crops[i], features[i] = studio.render_sample(material, rng)
            targets[i] = sample_properties(material, rng).targets()
            material_index[i] = k
            if progress is not None and (i % 50 == 0 or i == num_samples - 1):
                progress(f"rendering objects (seed {seed})", i + 1, num_samples)
    finally:
        studio.close()
    return PropertyDataset(crops=crops, shape_features=features, targets=targets, material=material_index, seed=seed)
