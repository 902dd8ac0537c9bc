"""Colour textures for reconstructed meshes, baked from the video frames.

MuJoCo displays 2D textures through per-vertex texture coordinates, not vertex colours, so each object mesh gets
a UV atlas (xatlas) and a texture image whose texels are coloured from the frames that see them:

1. unwrap with xatlas (vertices on chart seams are duplicated);
2. rasterise every chart in texture space: each texel gets its 3D surface point and face normal (barycentric);
3. per view: project the points (pinhole + radial distortion), keep those inside the image and facing the camera
   (cos(normal, ray) >= `min_cos_view`), and not occluded (a ray from the camera centre must reach the point:
   Open3D `RaycastingScene` on the mesh plus any occluders);
4. blend the `max_views_per_texel` best views (weight = cos / distance^2, i.e. surface pixel density), after
   dropping a sample that disagrees with the others' median colour (an occluder missing from the mesh, a
   specular highlight);
5. texels no view sees (the bottom resting on the table) take the inverse-distance mean colour of the nearest seen
   surface points in 3D; texels outside every chart take the colour of the nearest chart texel, so bilinear
   filtering and mipmapping never pull in black.

Conventions: pixel coordinates follow COLMAP (centre of the upper-left pixel at (0.5, 0.5)); texture coordinates
follow OBJ (v = 0 is the image's bottom row); the texture image's row 0 is its top. Inside this module `col`/`row`
are array coordinates (first pixel centre at 0), as `cv2.remap` wants them.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import cv2
import numpy as np

from reconstruction._types import CameraIntrinsics, TexturedMesh

if TYPE_CHECKING:
    from open3d.t.geometry import RaycastingScene

# Texels within this many texels outside a UV triangle are coloured too (from the clamped surface point), so
# bilinear lookups at a chart's border read real colours rather than extrapolated ones.
_BORDER_TEXELS = 1.0
# Candidate texels rasterised per batch (bounds memory for large textures or many faces).
_RASTER_BATCH = 2_000_000
# Seen texels used as sources when filling the unseen ones.
_FILL_SOURCES = 10_000


@dataclass(frozen=True, kw_only=True)
class TextureView:
    """One frame to take colours from.

    Attributes:
        image_bgr: (H, W, 3) uint8 frame as OpenCV decodes it; H, W must match the intrinsics.
        world_from_cam: (4, 4) camera-to-world rigid transform (OpenCV axes: x right, y down, z forward), in the
            same world frame and units as the mesh.
        intrinsics: fx, fy, cx, cy (COLMAP pixel convention) and radial k1, k2 of the SIMPLE_RADIAL / RADIAL
            models: distorted normalised coordinates x_d = x (1 + k1 r^2 + k2 r^4).
    """

    image_bgr: np.ndarray
    world_from_cam: np.ndarray
    intrinsics: CameraIntrinsics

    def __post_init__(self) -> None:
        image = self.image_bgr
        if not isinstance(image, np.ndarray) or image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
            shape = getattr(image, "shape", None)
            dtype = getattr(image, "dtype", type(image).__name__)
            raise ValueError(f"image_bgr has shape {shape} and dtype {dtype} but expected (H, W, 3) uint8")
        intr = self.intrinsics
        if image.shape[:2] != (intr.height_px, intr.width_px):
            raise ValueError(
                f"image_bgr is {image.shape[1]}x{image.shape[0]} px but the intrinsics say "
                f"{intr.width_px}x{intr.height_px}; pass the frame at the resolution it was calibrated at"
            )
        if not (intr.fx_px > 0 and intr.fy_px > 0 and np.isfinite([intr.cx_px, intr.cy_px, intr.k1, intr.k2]).all()):
            raise ValueError(f"intrinsics need positive fx, fy and finite cx, cy, k1, k2; got {intr}")
        pose = np.asarray(self.world_from_cam)
        if pose.shape != (4, 4) or not np.isfinite(pose).all():
            raise ValueError(f"world_from_cam.shape={pose.shape} but expected a finite (4, 4) rigid transform")
        rotation = pose[:3, :3]
        if (
            not np.allclose(pose[3], [0.0, 0.0, 0.0, 1.0], atol=1e-6)
            or not np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-4)
            or np.linalg.det(rotation) < 0
        ):
            raise ValueError("world_from_cam is not a rigid transform (rotation block not orthonormal, or scaled)")


@dataclass(frozen=True, kw_only=True)
class TextureOptions:
    """Texture baking settings.

    Attributes:
        texture_size_px: side of the square texture image.
        max_views_per_texel: blend at most this many views per texel (the best by cos / distance^2).
        min_cos_view: a view sees a surface point only when cos(normal, direction to the camera) is at least this
            (0.2 = 78 degrees from the normal): grazing views smear the texture.
        padding_px: minimum gap between UV charts in texels (xatlas packing); texels outside every chart are then
            all filled with the nearest chart colour, so mipmapping does not bleed black into the charts.
        seed: seed of the random subsets drawn (sources of the hole filling, samples of `texture_coverage`).
        max_views: when given more views, keep this many spread as evenly as possible around the mesh.
        outlier_threshold: with three or more candidate views, a sample whose mean absolute difference from the
            candidates' median colour exceeds this (0..255) is dropped.
        occlusion_tolerance_m, occlusion_tolerance_rel: a point is visible when the first hit of the ray from the
            camera centre lies within tolerance_m + tolerance_rel * distance of the point.
    """

    texture_size_px: int = 512
    max_views_per_texel: int = 3
    min_cos_view: float = 0.2
    padding_px: int = 4
    seed: int = 0
    max_views: int = 24
    outlier_threshold: float = 40.0
    occlusion_tolerance_m: float = 0.002
    occlusion_tolerance_rel: float = 0.005

    def __post_init__(self) -> None:
        if not 16 <= self.texture_size_px <= 8192:
            raise ValueError(f"texture_size_px={self.texture_size_px} but expected 16..8192")
        if self.max_views_per_texel < 1 or self.max_views < 1:
            raise ValueError(f"{self.max_views_per_texel=} and {self.max_views=} must be at least 1")
        if not 0.0 <= self.min_cos_view < 1.0:
            raise ValueError(f"min_cos_view={self.min_cos_view} but expected 0 <= min_cos_view < 1")
        if self.padding_px < 0:
            raise ValueError(f"padding_px={self.padding_px} but expected >= 0")
        if self.outlier_threshold <= 0 or self.occlusion_tolerance_m < 0 or self.occlusion_tolerance_rel < 0:
            raise ValueError("outlier_threshold must be positive and the occlusion tolerances non-negative")


@dataclass(frozen=True, kw_only=True)
class TextureBake:
    """A baked texture and how much of the surface the views actually saw.

    Attributes:
        mesh: the unwrapped mesh (same frame as the input vertices; faces in input order) with uv and texture.
        coverage: fraction of the surface area seen by at least one view (0..1); the rest is filled from neighbours.
        face_seen_fraction: (F,) float64 fraction of each face's texels seen by a view; NaN for faces too small to
            own a texel. Indexed like the input faces.
        view_indices: indices into the given views of those used (after spreading them out).
        seconds: wall time of the bake.
        stage_seconds: wall time of each step (select_views, unwrap, rasterise, ...).
    """

    mesh: TexturedMesh
    coverage: float
    face_seen_fraction: np.ndarray
    view_indices: tuple[int, ...]
    seconds: float
    stage_seconds: dict[str, float]


def bake_texture(
    vertices_world_m: np.ndarray,
    faces: np.ndarray,
    views: Sequence[TextureView],
    options: TextureOptions | None = None,
    *,
    occluders: Sequence[tuple[np.ndarray, np.ndarray]] = (),
) -> TexturedMesh:
    """UV-unwraps a mesh and bakes a colour texture for it from calibrated frames.

    Args:
        vertices_world_m: (V, 3) float vertex positions in the world frame of the views' poses.
        faces: (F, 3) int vertex indices, counter-clockwise seen from outside (normals point out).
        views: frames with their poses and intrinsics (more than `options.max_views` are thinned out).
        options: baking settings.
        occluders: other meshes of the scene, each (vertices_world_m (N, 3), faces (M, 3)), which may hide this
            one in some views (the other objects); they only block rays.

    Returns:
        The mesh with duplicated seam vertices (still in the given frame), (V', 2) uv in [0, 1] (OBJ convention)
        and a (S, S, 3) uint8 RGB texture (row 0 at the top).

    Raises:
        ValueError: malformed mesh, views or occluders, or no view sees any part of the mesh.
    """
    return bake_texture_report(vertices_world_m, faces, views, options, occluders=occluders).mesh


def bake_texture_report(
    vertices_world_m: np.ndarray,
    faces: np.ndarray,
    views: Sequence[TextureView],
    options: TextureOptions | None = None,
    *,
    occluders: Sequence[tuple[np.ndarray, np.ndarray]] = (),
) -> TextureBake:
    """`bake_texture`, also returning the coverage of the surface by the views (for reports); same arguments."""
    start_s = time.perf_counter()
    options = options or TextureOptions()
    vertices, faces_i = _validated_mesh(vertices_world_m, faces, what="mesh")
    _validate_views(views)
    occluder_meshes = [_validated_mesh(v, f, what=f"occluder {i}") for i, (v, f) in enumerate(occluders)]

    stage_s: dict[str, float] = {}
    tick = time.perf_counter()

    def lap(name: str) -> None:
        nonlocal tick
        now = time.perf_counter()
        stage_s[name] = now - tick
        tick = now

    view_ids = _select_views(vertices, views, options.max_views)
    lap("select_views")
    if not view_ids:
        raise ValueError(
            f"none of the {len(views)} views sees the mesh (no vertex projects into any image); check that the "
            "mesh and the camera poses are in the same world frame"
        )
    chosen = [views[i] for i in view_ids]

    vmapping, faces_uv, uv = _unwrap(vertices, faces_i, options)
    lap("unwrap")
    size = options.texture_size_px
    texels = _rasterise(uv, faces_uv, size)
    lap("rasterise")
    tri_world = vertices[faces_i]  # (F, 3, 3)
    points_m = np.einsum("tk,tkj->tj", texels.bary, tri_world[texels.face])
    normals = _face_normals(tri_world)[texels.face]

    scene = _raycasting_scene([(vertices, faces_i), *occluder_meshes])
    lap("raycasting_scene")
    colour_bgr, seen = _blend_views(points_m, normals, chosen, scene, options)
    lap("blend_views")
    if not seen.any():
        raise ValueError(
            f"no surface point of the mesh is visible in any of the {len(chosen)} views (all occluded, grazing or "
            "outside the images); check the poses or lower min_cos_view"
        )
    colour_bgr = _fill_unseen(points_m, colour_bgr, seen, options.seed)
    lap("fill_unseen")

    texture_bgr = np.zeros((size * size, 3), np.float32)
    texture_bgr[texels.flat_index] = colour_bgr
    texture_bgr = _extend_charts(texture_bgr.reshape(size, size, 3), texels.flat_index)
    texture_rgb = cv2.cvtColor(np.clip(np.rint(texture_bgr), 0, 255).astype(np.uint8), cv2.COLOR_BGR2RGB)
    lap("extend_charts")

    # Coverage by area: each texel strictly inside its face stands for face area / face texel area.
    areas_m2 = 0.5 * np.linalg.norm(
        np.cross(tri_world[:, 1] - tri_world[:, 0], tri_world[:, 2] - tri_world[:, 0]), axis=1
    )
    inside = texels.inside
    texel_area_m2 = areas_m2[texels.face[inside]] / np.maximum(texels.face_area_px[texels.face[inside]], 1e-12)
    coverage = float(np.sum(texel_area_m2 * seen[inside]) / max(np.sum(texel_area_m2), 1e-30))
    num_faces = len(faces_i)
    counts = np.bincount(texels.face[inside], minlength=num_faces).astype(np.float64)
    seen_counts = np.bincount(texels.face[inside], weights=seen[inside], minlength=num_faces)
    with np.errstate(invalid="ignore", divide="ignore"):
        face_seen = np.where(counts > 0, seen_counts / counts, np.nan)

    mesh = TexturedMesh(
        vertices_m=vertices[vmapping],
        faces=faces_uv.astype(np.int64),
        uv=uv.astype(np.float64),
        texture_rgb=texture_rgb,
    )
    return TextureBake(
        mesh=mesh,
        coverage=coverage,
        face_seen_fraction=face_seen,
        view_indices=tuple(view_ids),
        seconds=time.perf_counter() - start_s,
        stage_seconds=stage_s,
    )


def texture_coverage(
    vertices_world_m: np.ndarray,
    faces: np.ndarray,
    views: Sequence[TextureView],
    options: TextureOptions | None = None,
    *,
    occluders: Sequence[tuple[np.ndarray, np.ndarray]] = (),
    num_samples: int = 20_000,
) -> float:
    """Fraction of the surface area seen by at least one view, without baking (same visibility test).

    Samples `num_samples` points uniformly by area (seeded by `options.seed`), so it is an estimate with a
    standard error of about sqrt(c (1 - c) / num_samples).
    """
    options = options or TextureOptions()
    vertices, faces_i = _validated_mesh(vertices_world_m, faces, what="mesh")
    _validate_views(views)
    occluder_meshes = [_validated_mesh(v, f, what=f"occluder {i}") for i, (v, f) in enumerate(occluders)]
    if num_samples < 1:
        raise ValueError(f"num_samples={num_samples} but expected at least 1")
    view_ids = _select_views(vertices, views, options.max_views)
    if not view_ids:
        return 0.0
    tri = vertices[faces_i]
    areas = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    if areas.sum() <= 0:
        raise ValueError("the mesh has zero surface area")
    rng = np.random.default_rng(options.seed)
    face = rng.choice(len(faces_i), size=num_samples, p=areas / areas.sum())
    r1, r2 = np.sqrt(rng.random(num_samples)), rng.random(num_samples)
    bary = np.stack([1 - r1, r1 * (1 - r2), r1 * r2], axis=1)
    points = np.einsum("tk,tkj->tj", bary, tri[face])
    normals = _face_normals(tri)[face]
    scene = _raycasting_scene([(vertices, faces_i), *occluder_meshes])
    plane_offset = np.einsum("ij,ij->i", normals, points)
    seen = np.zeros(num_samples, bool)
    for i in view_ids:
        seen |= _view_weights(points, normals, plane_offset, views[i], scene, options)[0] > 0
    return float(seen.mean())


# ---------------------------------------------------------------- validation and view choice


def _validated_mesh(vertices: np.ndarray, faces: np.ndarray, *, what: str) -> tuple[np.ndarray, np.ndarray]:
    v = np.asarray(vertices)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) < 3:
        raise ValueError(f"{what}: vertices.shape={v.shape} but expected (V, 3) with V >= 3")
    if not np.issubdtype(v.dtype, np.number) or not np.isfinite(v).all():
        raise ValueError(f"{what}: vertices must be finite numbers")
    if f.ndim != 2 or f.shape[1] != 3 or len(f) < 1:
        raise ValueError(f"{what}: faces.shape={f.shape} but expected (F, 3) with F >= 1")
    if not np.issubdtype(f.dtype, np.integer):
        raise ValueError(f"{what}: faces.dtype={f.dtype} but expected integer vertex indices")
    if f.min() < 0 or f.max() >= len(v):
        raise ValueError(f"{what}: face indices span {f.min()}..{f.max()} but there are {len(v)} vertices")
    return v.astype(np.float64), f.astype(np.int64)


def _validate_views(views: Sequence[TextureView]) -> None:
    if len(views) == 0:
        raise ValueError("views is empty; pass at least one TextureView (frame, pose, intrinsics)")
    for i, view in enumerate(views):
        if not isinstance(view, TextureView):
            raise ValueError(f"views[{i}] is a {type(view).__name__} but expected a TextureView")


def _select_views(vertices: np.ndarray, views: Sequence[TextureView], max_views: int) -> list[int]:
    """Indices of the views that see the mesh, at most `max_views`, spread by farthest-point sampling.

    Views are compared by the direction from the mesh centre to their camera centre; the first pick is the view
    in which the most vertices project into the image.
    """
    step = max(1, len(vertices) // 500)
    sample = vertices[::step]
    centre = 0.5 * (vertices.min(axis=0) + vertices.max(axis=0))
    scores, directions = [], []
    for view in views:
        _, _, ok = _project(sample, view)
        scores.append(float(ok.mean()))
        offset = view.world_from_cam[:3, 3] - centre
        directions.append(offset / max(float(np.linalg.norm(offset)), 1e-12))
    candidates = [i for i, s in enumerate(scores) if s > 0]
    if len(candidates) <= max_views:
        return candidates
    dirs = np.asarray(directions)[candidates]
    score = np.asarray(scores)[candidates]
    picked = [int(np.argmax(score))]
    min_angle = np.arccos(np.clip(dirs @ dirs[picked[0]], -1, 1))
    while len(picked) < max_views:
        # Ties (identical viewpoints) go to the view that sees more of the mesh.
        nxt = int(np.lexsort((-score, -min_angle))[0])
        picked.append(nxt)
        min_angle = np.minimum(min_angle, np.arccos(np.clip(dirs @ dirs[nxt], -1, 1)))
    return sorted(candidates[i] for i in picked)


# ---------------------------------------------------------------- unwrapping and rasterisation


def _unwrap(vertices: np.ndarray, faces: np.ndarray, options: TextureOptions) -> tuple[np.ndarray, ...]:
    """xatlas charts packed into one atlas: (vmapping (V',), faces (F, 3), uv (V', 2) in [0, 1])."""
    import xatlas

    atlas = xatlas.Atlas()
    # Centred float32 positions: xatlas works in float32 and only shapes matter to it.
    centre = vertices.mean(axis=0)
    atlas.add_mesh((vertices - centre).astype(np.float32), faces.astype(np.uint32))
    chart_options = xatlas.ChartOptions()
    pack_options = xatlas.PackOptions()
    pack_options.resolution = options.texture_size_px
    # xatlas packs into at most `resolution` texels (often fewer); we rasterise the normalised uv at the full
    # size, so the gap between charts is at least padding_px.
    pack_options.padding = options.padding_px
    pack_options.bilinear = True
    atlas.generate(chart_options, pack_options)
    if atlas.atlas_count != 1:
        raise ValueError(f"xatlas packed the mesh into {atlas.atlas_count} atlases; expected one")
    vmapping, faces_uv, uv = atlas[0]
    if len(faces_uv) != len(faces):
        raise ValueError(f"xatlas returned {len(faces_uv)} faces for {len(faces)}; the mesh may be degenerate")
    return vmapping.astype(np.int64), faces_uv.astype(np.int64), np.clip(uv.astype(np.float64), 0.0, 1.0)


@dataclass(frozen=True, kw_only=True)
class _Texels:
    """Texels covered by the charts: flat index row * S + col, face, barycentrics (T, 3), strictly inside."""

    flat_index: np.ndarray
    face: np.ndarray
    bary: np.ndarray
    inside: np.ndarray
    face_area_px: np.ndarray  # (F,) area of each face in texels


def _rasterise(uv: np.ndarray, faces: np.ndarray, size: int) -> _Texels:
    """Texels whose centre lies in a UV triangle or within `_BORDER_TEXELS` of one (barycentrics then clamped)."""
    # Texture space in texels: x right, y down from the top row (OBJ v = 0 is the bottom row).
    tri = np.stack([uv[faces][..., 0] * size, (1.0 - uv[faces][..., 1]) * size], axis=-1)  # (F, 3, 2)
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    twice_area = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    edge_len = np.stack(
        [np.linalg.norm(c - b, axis=1), np.linalg.norm(a - c, axis=1), np.linalg.norm(b - a, axis=1)], axis=1
    )
    valid = np.abs(twice_area) > 1e-9
    lo = np.floor(tri.min(axis=1) - _BORDER_TEXELS - 0.5).astype(np.int64)
    hi = np.ceil(tri.max(axis=1) + _BORDER_TEXELS - 0.5).astype(np.int64)
    lo = np.clip(lo, 0, size - 1)
    hi = np.clip(hi, 0, size - 1)
    nx = np.where(valid, hi[:, 0] - lo[:, 0] + 1, 0)
    ny = np.where(valid, hi[:, 1] - lo[:, 1] + 1, 0)
    counts = nx * ny

    parts: list[tuple[np.ndarray, ...]] = []
    face_ids = np.flatnonzero(counts)
    batches = np.split(face_ids, np.flatnonzero(np.diff(np.cumsum(counts[face_ids]) // _RASTER_BATCH)) + 1)
    for batch in batches:
        if len(batch) == 0:
            continue
        n = counts[batch]
        face = np.repeat(batch, n)
        local = np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)
        col = lo[face, 0] + local % nx[face]
        row = lo[face, 1] + local // nx[face]
        p = np.stack([col + 0.5, row + 0.5], axis=1)
        pa, pb, pc = a[face] - p, b[face] - p, c[face] - p
        d = twice_area[face]
        w_a = (pb[:, 0] * pc[:, 1] - pb[:, 1] * pc[:, 0]) / d
        w_b = (pc[:, 0] * pa[:, 1] - pc[:, 1] * pa[:, 0]) / d
        bary = np.stack([w_a, w_b, 1.0 - w_a - w_b], axis=1)
        # Signed distance (texels) to each edge line, positive inside.
        dist_px = (bary * np.abs(d)[:, None] / np.maximum(edge_len[face], 1e-12)).min(axis=1)
        keep = dist_px >= -_BORDER_TEXELS
        parts.append((row[keep] * size + col[keep], face[keep], bary[keep], dist_px[keep]))
    if not parts:
        raise ValueError("the UV atlas has no texel inside any triangle; the mesh is degenerate")
    flat, face, bary, dist_px = (np.concatenate(x) for x in zip(*parts, strict=True))
    # One face per texel: the one containing it, else the nearest (charts are >= padding apart, so border texels of
    # different charts rarely compete).
    order = np.lexsort((-dist_px, flat))
    flat, face, bary, dist_px = flat[order], face[order], bary[order], dist_px[order]
    first = np.r_[True, flat[1:] != flat[:-1]]
    flat, face, bary, dist_px = flat[first], face[first], bary[first], dist_px[first]
    inside = dist_px >= 0
    bary = np.clip(bary, 0.0, None)
    bary /= bary.sum(axis=1, keepdims=True)
    return _Texels(flat_index=flat, face=face, bary=bary, inside=inside, face_area_px=0.5 * np.abs(twice_area))


def _face_normals(tri: np.ndarray) -> np.ndarray:
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)


# ---------------------------------------------------------------- visibility and colour


def _raycasting_scene(meshes: list[tuple[np.ndarray, np.ndarray]]) -> RaycastingScene:
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    for vertices, faces in meshes:
        scene.add_triangles(
            o3d.core.Tensor.from_numpy(np.ascontiguousarray(vertices, np.float32)),
            o3d.core.Tensor.from_numpy(np.ascontiguousarray(faces, np.uint32)),
        )
    return scene


def _project(points: np.ndarray, view: TextureView) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Array pixel coordinates (col, row; first pixel centre at 0) of (N, 3) world points, and which land inside.

    A point is inside when it is in front of the camera, within the radius where the radial distortion is still
    monotonic (beyond it, points far outside the view fold back into the image), and its bilinear footprint is in
    the image.
    """
    intr = view.intrinsics
    rotation, centre = view.world_from_cam[:3, :3], view.world_from_cam[:3, 3]
    # einsum, not `@`: a multithreaded BLAS call per view fights Open3D's ray-casting threads for the cores
    # (measured 1.6x slower overall on 2 cores).
    p_cam = np.einsum("ni,ij->nj", points - centre, rotation)
    z = p_cam[:, 2]
    front = z > 1e-9
    z_safe = np.where(front, z, 1.0)
    x, y = p_cam[:, 0] / z_safe, p_cam[:, 1] / z_safe
    r2 = x * x + y * y
    radial = 1.0 + intr.k1 * r2 + intr.k2 * r2 * r2
    monotonic = 1.0 + 3.0 * intr.k1 * r2 + 5.0 * intr.k2 * r2 * r2 > 0
    col = intr.fx_px * x * radial + intr.cx_px - 0.5  # COLMAP -> array coordinates
    row = intr.fy_px * y * radial + intr.cy_px - 0.5
    ok = front & monotonic & (col >= 0) & (col <= intr.width_px - 1) & (row >= 0) & (row <= intr.height_px - 1)
    return col, row, ok


def _view_weights(
    points: np.ndarray,
    normals: np.ndarray,
    plane_offset: np.ndarray,
    view: TextureView,
    scene: RaycastingScene,
    options: TextureOptions,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Blend weight of one view for each surface point (0 = unseen) and its array pixel coordinates.

    Args:
        points: (N, 3) surface points, world frame.
        normals: (N, 3) unit outward normals.
        plane_offset: (N,) normals . points (the tangent planes), shared by all views.

    Returns:
        weight (N,) float32 (cos / distance^2 where visible, else 0), col (N,) and row (N,) float32 array pixel
        coordinates (meaningful where weight > 0).
    """
    import open3d as o3d

    centre = view.world_from_cam[:3, 3]
    num = len(points)
    weight = np.zeros(num, np.float32)
    col = np.zeros(num, np.float32)
    row = np.zeros(num, np.float32)
    # Height of the camera above each tangent plane: cheap back-face culling before projecting anything.
    height = np.einsum("ni,i->n", normals, centre) - plane_offset
    facing = np.flatnonzero(height > 0)
    if len(facing) == 0:
        return weight, col, row
    p = points[facing]
    c, r, ok = _project(p, view)
    to_cam = centre - p
    dist = np.linalg.norm(to_cam, axis=1)
    cos = height[facing] / np.maximum(dist, 1e-12)
    candidates = np.flatnonzero(ok & (cos >= options.min_cos_view))
    if len(candidates) == 0:
        return weight, col, row
    d = dist[candidates]
    rays = np.empty((len(candidates), 6), np.float32)
    rays[:, :3] = centre
    rays[:, 3:] = -to_cam[candidates] / d[:, None]
    t_hit = scene.cast_rays(o3d.core.Tensor.from_numpy(rays))["t_hit"].numpy()
    tolerance = options.occlusion_tolerance_m + options.occlusion_tolerance_rel * d
    visible = t_hit >= d - tolerance  # inf (a miss, only by rounding) counts as visible
    keep = candidates[visible]
    # Surface pixel density: the image area of a surface patch goes as cos / distance^2.
    weight[facing[keep]] = cos[keep] / np.square(dist[keep])
    col[facing] = c
    row[facing] = r
    return weight, col, row


def nanmedian_first_axis(samples: np.ndarray) -> np.ndarray:
    """``np.nanmedian(samples, axis=0)`` (NaN where a column has no number), value for value, without the warning.

    NumPy takes the median of a few rows over many columns through masked arrays: 3.6 s of the tabletop sample's
    grounding for its table drawing and texture, against 0.2 s sorted once here (NaN sorts last).
    """
    ordered = np.sort(samples, axis=0)
    counts = np.sum(~np.isnan(samples), axis=0)
    low = np.take_along_axis(ordered, np.maximum((counts - 1) // 2, 0)[None], axis=0)[0]
    high = np.take_along_axis(ordered, (counts // 2)[None], axis=0)[0]
    middle = (low + high) / 2
    return np.where(counts > 0, middle, np.nan).astype(samples.dtype, copy=False)


def _sample_bilinear(image_bgr: np.ndarray, col: np.ndarray, row: np.ndarray) -> np.ndarray:
    """(N, 3) float32 bilinear samples at array coordinates (cv2.remap wants 2D maps of bounded width)."""
    n = len(col)
    width = 1024
    padded = -(-n // width) * width
    map_x = np.zeros(padded, np.float32)
    map_y = np.zeros(padded, np.float32)
    map_x[:n], map_y[:n] = col, row
    out = cv2.remap(
        np.ascontiguousarray(image_bgr),
        map_x.reshape(-1, width),
        map_y.reshape(-1, width),
        interpolation=cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    )
    return out.reshape(-1, 3)[:n].astype(np.float32)


def _blend_views(
    points: np.ndarray,
    normals: np.ndarray,
    views: list[TextureView],
    scene: RaycastingScene,
    options: TextureOptions,
) -> tuple[np.ndarray, np.ndarray]:
    """Blended BGR colour (T, 3) float32 and seen mask (T,) of every texel point."""
    num = len(points)
    weights = np.zeros((len(views), num), np.float32)
    coords: list[tuple[np.ndarray, np.ndarray]] = []
    plane_offset = np.einsum("ij,ij->i", normals, points)
    for i, view in enumerate(views):
        weights[i], col, row = _view_weights(points, normals, plane_offset, view, scene, options)
        coords.append((col, row))
    k = min(options.max_views_per_texel, len(views))
    if k < len(views):
        best = np.argpartition(-weights, k - 1, axis=0)[:k]  # (k, T) view index per slot
    else:
        best = np.broadcast_to(np.arange(len(views))[:, None], (k, num))
    best_w = np.take_along_axis(weights, best, axis=0)
    samples = np.zeros((k, num, 3), np.float32)
    for i, view in enumerate(views):
        slots, texels = np.nonzero((best == i) & (best_w > 0))
        if len(texels) == 0:
            continue
        col, row = coords[i]
        samples[slots, texels] = _sample_bilinear(view.image_bgr, col[texels], row[texels])

    valid = best_w > 0
    num_valid = valid.sum(axis=0)
    robust = num_valid >= 3
    if robust.any():
        # Per-channel median of the candidate samples; drop the ones far from it (occluders missing from the scene
        # mesh, specular highlights), unless that would drop every sample.
        cand = samples[:, robust]
        cand_valid = valid[:, robust]
        ordered = np.sort(np.where(cand_valid[..., None], cand, np.inf), axis=0)  # invalid samples sort last
        n = num_valid[robust]
        shape = (1, len(n), 3)
        lower = np.broadcast_to(((n - 1) // 2)[None, :, None], shape)
        upper = np.broadcast_to((n // 2)[None, :, None], shape)
        median = 0.5 * (np.take_along_axis(ordered, lower, 0) + np.take_along_axis(ordered, upper, 0))
        agree = cand_valid & (np.abs(cand - median).mean(axis=2) <= options.outlier_threshold)
        none_agree = ~agree.any(axis=0)
        agree[:, none_agree] = cand_valid[:, none_agree]
        valid[:, robust] = agree
    w = np.where(valid, best_w, 0.0).astype(np.float32)
    total = w.sum(axis=0)
    seen = total > 0
    colour = np.zeros((num, 3), np.float32)
    colour[seen] = np.einsum("kt,ktc->tc", w[:, seen], samples[:, seen]) / total[seen, None]
    return colour, seen


def _fill_unseen(points: np.ndarray, colour: np.ndarray, seen: np.ndarray, seed: int) -> np.ndarray:
    """Colours texels no view saw with the inverse-distance mean of the nearest seen surface points in 3D.

    At most `_FILL_SOURCES` seen points (a seeded random subset) serve as sources: the fill is smooth anyway, and a
    k-d tree query far from a large, nearly flat point set is slow.
    """
    from scipy.spatial import cKDTree

    unseen = np.flatnonzero(~seen)
    if len(unseen) == 0:
        return colour
    sources = np.flatnonzero(seen)
    if len(sources) > _FILL_SOURCES:
        sources = np.sort(np.random.default_rng(seed).choice(sources, _FILL_SOURCES, replace=False))
    k = min(8, len(sources))
    dist, nearest = cKDTree(points[sources]).query(points[unseen], k=k, eps=0.5)
    dist = dist.reshape(len(unseen), k)
    nearest = nearest.reshape(len(unseen), k)
    w = 1.0 / (dist + 1e-6)
    out = colour.copy()
    out[unseen] = np.einsum("uk,ukc->uc", w, colour[sources][nearest]) / w.sum(axis=1, keepdims=True)
    return out


def _extend_charts(texture: np.ndarray, chart_flat: np.ndarray) -> np.ndarray:
    """Gives every texel outside the charts the colour of the nearest chart texel (padding for mipmaps)."""
    size = texture.shape[0]
    outside = np.ones(size * size, np.uint8)
    outside[chart_flat] = 0
    if not outside.any():
        return texture
    _, labels = cv2.distanceTransformWithLabels(
        outside.reshape(size, size), cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL
    )
    labels = labels.ravel()
    # With DIST_LABEL_PIXEL each chart texel is its own label; every texel carries its nearest chart texel's label.
    source_of_label = np.zeros(int(labels.max()) + 1, np.int64)
    source_of_label[labels[chart_flat]] = chart_flat
    flat = texture.reshape(-1, 3)
    return flat[source_of_label[labels]].reshape(texture.shape)


# ---------------------------------------------------------------- the table top


def bake_table_texture(
    views: Sequence[TextureView],
    half_extents_m: tuple[float, float],
    occluders_world: Sequence[tuple[np.ndarray, np.ndarray]],
    *,
    top_z_m: float = 0.0,
    metres_per_px: float = 0.002,
    max_side_px: int = 1024,
    max_views: int = 16,
) -> np.ndarray:
    """(H, W, 3) uint8 RGB image of the table top as the frames saw it: row 0 is the top's +y edge, column 0 its -x
    edge, one texel per `metres_per_px` (coarser when a side would exceed `max_side_px`).

    Each texel is the median colour over up to `max_views` frames spread over the capture that see it with no
    object in between (`occluders_world`: (vertices, faces) per object, world frame): the median drops the
    glints and the frames where an object's shadow or a hand passes. Texels no frame saw (under the objects,
    beyond the views) get the median colour of those seen.
    """
    import open3d as o3d

    _validate_views(views)
    hx, hy = half_extents_m
    step = max(metres_per_px, 2 * max(hx, hy) / max_side_px)
    cols, rows = max(2, round(2 * hx / step)), max(2, round(2 * hy / step))
    xs = -hx + (np.arange(cols) + 0.5) * (2 * hx / cols)
    ys = hy - (np.arange(rows) + 0.5) * (2 * hy / rows)
    grid_x, grid_y = np.meshgrid(xs, ys)
    texels = np.stack([grid_x.ravel(), grid_y.ravel(), np.full(grid_x.size, top_z_m)], axis=1)
    scene = _raycasting_scene(list(occluders_world)) if occluders_world else None
    picks = np.unique(np.linspace(0, len(views) - 1, min(max_views, len(views))).round().astype(int))
    samples = np.full((len(picks), len(texels), 3), np.nan, np.float32)
    for slot, v in enumerate(picks):
        view = views[v]
        col, row, ok = _project(texels, view)
        centre = view.world_from_cam[:3, 3]
        if scene is not None and ok.any():
            origins = texels[ok] + np.array([0.0, 0.0, 1e-4])
            to_cam = centre - origins
            distance = np.linalg.norm(to_cam, axis=1)
            rays = np.concatenate([origins, to_cam / distance[:, None]], axis=1).astype(np.float32)
            hits = scene.cast_rays(o3d.core.Tensor.from_numpy(rays))["t_hit"].numpy()
            visible = np.flatnonzero(ok)
            ok[visible[hits < distance]] = False
        if ok.any():
            samples[slot, ok] = _sample_bilinear(view.image_bgr, col[ok], row[ok])[:, ::-1]  # BGR -> RGB
    seen = ~np.isnan(samples[..., 0])
    counts = seen.sum(axis=0)
    colour = np.zeros((len(texels), 3), np.float32)
    observed = counts > 0
    if observed.any():
        colour[observed] = nanmedian_first_axis(samples[:, observed])
        colour[~observed] = np.median(colour[observed], axis=0)
    return np.clip(colour, 0, 255).round().astype(np.uint8).reshape(rows, cols, 3)
