"""Objects the stereo cannot see: silhouettes against the table, and their visual hull (world frame, table z = 0).

Stereo needs texture on the object; a plain ball or a white mug gives it none, and the fused surface misses it. Its
outline against the table is still plain to see. The table top as the frames saw it (per texel, the median colour
over frames spread over the capture: an object covers any one texel in a minority of them; static shadows are part
of the table) is drawn into every frame through the table plane's homography. Where a frame differs from that
drawing (a colour distance in CIE Lab after the frame's brightness is matched), it sees something standing on the
table. A cell of space above the table is kept when the frames that see it almost never see table there
(Laurentini's visual hull, with a tolerance for a few wrong labels); kept cells connected and resting on the table
are objects.

A visual hull closes cavities (a cup's inside) and is never smaller than the object, so it is used only where the
fused surface found nothing, or only a fragment of the piece (`reconstruction._scene_objects._with_silhouettes`).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage

from reconstruction._dense import RegionOfInterest, StereoView
from reconstruction._texture import _sample_bilinear, nanmedian_first_axis

log = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class SilhouetteOptions:
    """Silhouettes and visual hull settings.

    Attributes:
        max_image_size_px: longest side at which frames are compared with the table's drawing.
        table_views: frames (spread over the capture) whose median colour makes the table's drawing.
        colour_threshold: CIE Lab distance (L weighted by ``lightness_weight``) above which a pixel is not table.
        lightness_weight: weight of the lightness difference (shading changes it more than colour).
        blur_px: Gaussian blur of both images before comparing (resampling and noise).
        zncc_window_px, zncc_threshold: where both images vary, a pixel whose window correlates less than this
            with the drawing's (normalised cross-correlation of lightness) is not table either (-1: colour only).
        cell_voxels: hull cell size, in fused voxels.
        max_background_fraction: a cell is carved when more than this fraction of the frames that see it see table.
        min_foreground_views: a kept cell is seen as "not table" by at least this many frames.
        min_size_voxels: smallest object kept: a cube this many fused voxels wide.
        rest_cells: an object's lowest cell lies at most this many cells above the table (it rests on it).
        min_gap_voxels, min_fill_near: a piece nearer a fused object than this (fused voxels, on the table) that
            fills less than `min_fill_near` of its box of cells is the colour that object casts on the table, not
            an object: a glow seen from a pass leaves a thin cone (the real apple's red glow beside it filled 4.5%
            and became a second body 2 mm beside it). A solid piece that near is a neighbour (held-out 1006: two
            bottles 1 cm from a book, 47% full, were lost to a plain gap rule); objects filled 20-56% on tuning
            seeds 0-8, but for a plate's hull seen from a pass (7.4%, tuning seed 5), which that near is dropped.
        max_fragment_box_ratio: a fused object whose bounding box holds less than this fraction of the box of the
            one solid hull piece it meets is a fragment of that piece's object: the hull replaces it
            (`reconstruction._scene_objects._fragment_of`).
    """

    max_image_size_px: int = 320
    table_views: int = 24
    colour_threshold: float = 18.0
    lightness_weight: float = 0.5
    blur_px: float = 1.0
    zncc_window_px: int = 7
    zncc_threshold: float = 0.3
    cell_voxels: float = 2.0
    max_background_fraction: float = 0.1
    min_foreground_views: int = 6
    min_size_voxels: float = 6.0
    rest_cells: int = 2
    min_gap_voxels: float = 4.0
    min_fill_near: float = 0.12
    max_fragment_box_ratio: float = 0.2


@dataclass(frozen=True, kw_only=True)
class HullObject:
    """One connected piece of the visual hull (world frame)."""

    cells: np.ndarray  # (N, 3) int cell indices into the grid
    origin_world: np.ndarray  # (3,) centre of cell (0, 0, 0)
    cell_m: float

    @property
    def points_world(self) -> np.ndarray:
        return self.origin_world + self.cells * self.cell_m

    @property
    def fill(self) -> float:
        """The fraction of its box of cells the piece fills (a solid's hull fills much of it; a cone, little)."""
        return len(self.cells) / float(np.prod(np.ptp(self.cells, axis=0) + 1))


@dataclass(frozen=True, kw_only=True)
class VisualHull:
    """The pieces of the hull that rest on the table."""

    pieces: tuple[HullObject, ...]


@dataclass(frozen=True, kw_only=True)
class TableDrawing:
    """The table top as the frames saw it: texel (row, col) centre at ``origin_world + (col, row, 0) * step``."""

    image_lab: np.ndarray  # (H, W, 3) float32 CIE Lab, NaN where no frame saw it
    origin_world: np.ndarray  # (3,)
    step_m: float


def _scaled(views: Sequence[StereoView], k: np.ndarray, max_side: int) -> tuple[list[np.ndarray], np.ndarray]:
    h, w = views[0].image_bgr.shape[:2]
    scale = min(1.0, max_side / max(h, w))
    size = (max(1, round(w * scale)), max(1, round(h * scale)))
    images = [cv2.resize(v.image_bgr, size, interpolation=cv2.INTER_AREA) for v in views]
    ks = k.copy()
    ks[:2] *= scale
    ks[0, 2] = (k[0, 2] + 0.5) * scale - 0.5  # OpenCV pixel centres (first at 0)
    ks[1, 2] = (k[1, 2] + 0.5) * scale - 0.5
    return images, ks


def _lab(image_bgr: np.ndarray, blur_px: float) -> np.ndarray:
    image = np.asarray(image_bgr, np.float32) / np.float32(255.0)
    if blur_px > 0:
        image = np.asarray(cv2.GaussianBlur(image, (0, 0), blur_px), np.float32)
    return np.asarray(cv2.cvtColor(image, cv2.COLOR_BGR2LAB))


def _project(points_world: np.ndarray, world_from_cam: np.ndarray, k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 2) OpenCV pixel coordinates (NaN for points at or behind the camera) and (N,) depth of world points."""
    # K [R | t] in one product per point (the visual hull's grid holds up to a few million cells, seen by every frame)
    pix_from_world = k @ np.linalg.inv(world_from_cam)[:3]
    homogeneous = points_world @ pix_from_world[:, :3].T + pix_from_world[:, 3]
    depth = homogeneous[:, 2]
    safe = np.where(depth > 1e-9, depth, np.nan)
    return homogeneous[:, :2] / safe[:, None], depth


def table_drawing(
    images_lab: Sequence[np.ndarray],
    views: Sequence[StereoView],
    k: np.ndarray,
    lo_xy: np.ndarray,
    hi_xy: np.ndarray,
    step_m: float,
    num_views: int,
) -> TableDrawing:
    """The median colour of every texel of the table top between `lo_xy` and `hi_xy` (world frame, metres)."""
    cols = max(2, int(np.ceil((hi_xy[0] - lo_xy[0]) / step_m)))
    rows = max(2, int(np.ceil((hi_xy[1] - lo_xy[1]) / step_m)))
    origin = np.array([lo_xy[0] + 0.5 * step_m, lo_xy[1] + 0.5 * step_m, 0.0])
    gx, gy = np.meshgrid(np.arange(cols), np.arange(rows))
    texels = origin + np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], axis=1) * step_m
    picks = np.unique(np.linspace(0, len(views) - 1, min(num_views, len(views))).round().astype(int))
    samples = np.full((len(picks), len(texels), 3), np.nan, np.float32)
    for slot, i in enumerate(picks):
        uv, depth = _project(texels, views[i].world_from_cam, k)
        h, w = images_lab[i].shape[:2]
        ok = (depth > 0) & (uv[:, 0] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= h - 1)
        if ok.any():
            samples[slot, ok] = _sample_bilinear(images_lab[i], uv[ok, 0], uv[ok, 1])
    colour = nanmedian_first_axis(samples)  # texels no frame saw: NaN
    return TableDrawing(image_lab=colour.reshape(rows, cols, 3), origin_world=origin, step_m=step_m)


def _zncc(a: np.ndarray, b: np.ndarray, valid: np.ndarray, window: int) -> tuple[np.ndarray, np.ndarray]:
    """Zero-mean normalised cross-correlation of two lightness images over `window` x `window` pixels, and where
    both vary enough for it to mean something (a standard deviation of at least 2 L units)."""
    a = np.where(valid, a, 0).astype(np.float32)
    b = np.where(valid, b, 0).astype(np.float32)
    size = (window, window)
    mean_a, mean_b = cv2.blur(a, size), cv2.blur(b, size)
    var_a = cv2.blur(a * a, size) - mean_a**2
    var_b = cv2.blur(b * b, size) - mean_b**2
    cov = cv2.blur(a * b, size) - mean_a * mean_b
    textured = (var_a > 4.0) & (var_b > 4.0)
    zncc = cov / np.sqrt(np.maximum(var_a * var_b, 1e-6))
    inside = ndimage.binary_erosion(valid, iterations=window // 2 + 1)
    return zncc, textured & inside


def not_table_mask(
    image_lab: np.ndarray, world_from_cam: np.ndarray, k: np.ndarray, table: TableDrawing, options: SilhouetteOptions
) -> np.ndarray:
    """(H, W) int8 per pixel: 1 where the frame sees the table as drawn, 2 where it sees something else, 0 where
    its ray misses the drawn table (above the horizon, beyond the drawing, texels no frame saw)."""
    h, w = image_lab.shape[:2]
    cam_from_world = np.linalg.inv(world_from_cam)
    # pixel -> texel: the inverse of texel -> pixel, K [r1 r2 t] A with A the texel grid's affine map to (x, y, 1)
    a = np.array(
        [[table.step_m, 0.0, table.origin_world[0]], [0.0, table.step_m, table.origin_world[1]], [0.0, 0.0, 1.0]]
    )
    h_pix_from_texel = k @ np.column_stack([cam_from_world[:3, 0], cam_from_world[:3, 1], cam_from_world[:3, 3]]) @ a
    h_texel_from_pix = np.linalg.inv(h_pix_from_texel)
    gu, gv = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    pix = np.stack([gu.ravel(), gv.ravel(), np.ones(gu.size)])
    texel = h_texel_from_pix @ pix
    # A pixel's ray meets the plane in front of the camera where the texel's depth (third row of K [r1 r2 t] A)
    # has the sign of a point in front: the depth of the texel the pixel maps to must be positive.
    depth = (np.column_stack([cam_from_world[2, 0], cam_from_world[2, 1], cam_from_world[2, 3]]) @ a) @ (
        texel / np.where(np.abs(texel[2]) > 1e-12, texel[2], 1e-12)
    )
    with np.errstate(all="ignore"):
        tx = (texel[0] / texel[2]).reshape(h, w).astype(np.float32)
        ty = (texel[1] / texel[2]).reshape(h, w).astype(np.float32)
    in_front = (depth.reshape(h, w) > 0) & np.isfinite(tx) & np.isfinite(ty)
    tx[~in_front] = -10
    ty[~in_front] = -10
    drawn = cv2.remap(table.image_lab, tx, ty, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)
    valid = in_front & np.isfinite(drawn).all(axis=2)
    labels = np.zeros((h, w), np.int8)
    if valid.sum() < 100:
        return labels
    # Match the frame's brightness to the drawing's (auto exposure): the median lightness ratio over valid pixels.
    gain = float(np.median(image_lab[..., 0][valid] + 1.0) / np.median(drawn[..., 0][valid] + 1.0))
    diff = image_lab - drawn * np.array([gain, 1.0, 1.0], np.float32)
    distance = np.sqrt(options.lightness_weight * diff[..., 0] ** 2 + diff[..., 1] ** 2 + diff[..., 2] ** 2)
    other = valid & (distance > options.colour_threshold)
    if options.zncc_threshold > -1:
        # Colour alone misses an object whose colour is the table's; the table's pattern then still differs.
        zncc, textured = _zncc(image_lab[..., 0], drawn[..., 0] * gain, valid, options.zncc_window_px)
        other |= valid & textured & (zncc < options.zncc_threshold)
    other = ndimage.binary_opening(other, iterations=1)
    other = ndimage.binary_fill_holes(ndimage.binary_closing(other, iterations=2)) & valid
    labels[valid] = 1
    labels[other] = 2
    return labels


def _label_counts(
    centres: np.ndarray,
    labels: Sequence[np.ndarray],
    views: Sequence[StereoView],
    k: np.ndarray,
    carve_fraction: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """(N,) frames that see table, and frames that see something else, at each of (N, 3) world points.

    With `carve_fraction` f, a point stops being looked at once it is carved whatever the frames left see: its table
    count b already exceeds f (b + o + r), o its other count and r the frames left. Its counts are then partial, but
    every decision `b > f * max(b + o, 1)` (carved) and its negation (kept) comes out as with every frame counted:
    b only grows and b + o grows by at most r. Most cells of the grid are empty space that the first few frames
    carve, so the grid is projected into the later frames only where something may stand.
    """
    background = np.zeros(len(centres), np.int32)
    foreground = np.zeros(len(centres), np.int32)
    alive = np.arange(len(centres))
    for index, (label, view) in enumerate(zip(labels, views, strict=True)):
        if not len(alive):
            break
        h, w = label.shape
        uv, depth = _project(centres[alive], view.world_from_cam, k)
        with np.errstate(invalid="ignore"):
            col = np.round(uv[:, 0])
            row = np.round(uv[:, 1])
            inside = np.flatnonzero((depth > 0) & (col >= 0) & (col < w) & (row >= 0) & (row < h))
        seen = label[row[inside].astype(int), col[inside].astype(int)]
        background[alive[inside[seen == 1]]] += 1
        foreground[alive[inside[seen == 2]]] += 1
        if carve_fraction is not None:
            left = len(views) - index - 1
            b, o = background[alive], foreground[alive]
            alive = alive[b <= carve_fraction * (b + o + left)]
    return background, foreground


def _without_footprints(table: TableDrawing, xy_world: np.ndarray, cell_m: float) -> TableDrawing:
    """The drawing with the texels under (and one cell around) `xy_world` made unknown: no frame sees the table
    under an object, and the drawing there holds the object's own colour."""
    image = table.image_lab.copy()
    rows, cols = image.shape[:2]
    index = np.round((xy_world - table.origin_world[:2]) / table.step_m).astype(int)
    mask = np.zeros((rows, cols), bool)
    ok = (index[:, 0] >= 0) & (index[:, 0] < cols) & (index[:, 1] >= 0) & (index[:, 1] < rows)
    mask[index[ok, 1], index[ok, 0]] = True
    reach = max(1, round(1.5 * cell_m / table.step_m))
    mask = ndimage.binary_dilation(mask, iterations=reach)
    image[mask] = np.nan
    return TableDrawing(image_lab=image, origin_world=table.origin_world, step_m=table.step_m)


def visual_hull(
    views: Sequence[StereoView],
    k: np.ndarray,
    roi: RegionOfInterest,
    voxel_m: float,
    options: SilhouetteOptions | None = None,
) -> VisualHull | None:
    """The visual hull inside `roi`: its connected pieces that rest on the table, largest first; None with too
    few frames for one.

    Each piece is grown down to the table through the cells no frame sees table at once the table under it is
    unknown (the drawing holds the object's colour there, so its lowest part was carved); a piece that cannot
    reach the table floats (a reflection, a mislabelled patch) and is no object.

    Args:
        views: registered frames (full-size images, OpenCV camera axes).
        k: (3, 3) intrinsics at the images' size, OpenCV pixel convention.
        roi: the region searched for objects (its z range: from the table up).
        voxel_m: the fused surface's voxel size (the hull's cell is a multiple of it).
    """
    options = options or SilhouetteOptions()
    if len(views) < options.min_foreground_views:
        return None
    images, ks = _scaled(views, k, options.max_image_size_px)
    images_lab = [_lab(im, options.blur_px) for im in images]
    cell = options.cell_voxels * voxel_m
    height = float(roi.max_world[2])
    # The drawing reaches past the region: a ray through a high cell meets the table beyond the region's side.
    lo_xy, hi_xy = roi.min_world[:2] - height, roi.max_world[:2] + height
    table = table_drawing(images_lab, views, ks, lo_xy, hi_xy, 0.5 * cell, options.table_views)
    labels = [not_table_mask(im, v.world_from_cam, ks, table, options) for im, v in zip(images_lab, views, strict=True)]

    shape = np.maximum(1, np.ceil((roi.max_world - np.array([*roi.min_world[:2], 0.0])) / cell).astype(int))
    origin = np.array([roi.min_world[0] + 0.5 * cell, roi.min_world[1] + 0.5 * cell, 0.5 * cell])
    ii, jj, kk = np.meshgrid(*(np.arange(n) for n in shape), indexing="ij")
    cells = np.stack([ii.ravel(), jj.ravel(), kk.ravel()], axis=1)
    background, foreground = _label_counts(origin + cells * cell, labels, views, ks, options.max_background_fraction)
    kept = (foreground >= options.min_foreground_views) & (
        background <= options.max_background_fraction * np.maximum(background + foreground, 1)
    )
    pieces, count = ndimage.label(kept.reshape(tuple(shape)))
    min_cells = (options.min_size_voxels * voxel_m / cell) ** 3
    candidates = [m for m in (np.argwhere(pieces == i) for i in range(1, count + 1)) if len(m) >= min_cells]
    if not candidates:
        return VisualHull(pieces=())

    # Second look under the pieces, with the table under them unknown.
    table = _without_footprints(table, origin[:2] + np.concatenate(candidates)[:, :2] * cell, cell)
    labels = [not_table_mask(im, v.world_from_cam, ks, table, options) for im, v in zip(images_lab, views, strict=True)]
    found = []
    for member in candidates:
        columns, lowest = _column_lowest(member)
        below = np.array([(x, y, z) for (x, y), top in zip(columns, lowest, strict=True) for z in range(top)], int)
        grown = member
        if len(below):
            bg, fg = _label_counts(origin + below * cell, labels, views, ks, options.max_background_fraction)
            carved = bg > options.max_background_fraction * np.maximum(bg + fg, 1)
            # A column grows down from its lowest cell through uncarved cells only, not past a carved one.
            stop = np.full(shape[:2], -1)
            np.maximum.at(stop, (below[carved, 0], below[carved, 1]), below[carved, 2])
            grown = np.vstack([member, below[below[:, 2] > stop[below[:, 0], below[:, 1]]]])
        if grown[:, 2].min() > options.rest_cells:
            log.info("a visual-hull piece of %d cells floats above the table: not an object", len(member))
            continue
        found.append(HullObject(cells=grown, origin_world=origin, cell_m=cell))
    found.sort(key=lambda h: -len(h.cells))
    return VisualHull(pieces=tuple(found))


def _column_lowest(member: np.ndarray) -> tuple[list[tuple[int, int]], list[int]]:
    order = np.lexsort((member[:, 2], member[:, 1], member[:, 0]))
    m = member[order]
    first = np.ones(len(m), bool)
    first[1:] = np.any(m[1:, :2] != m[:-1, :2], axis=1)
    return [tuple(c) for c in m[first, :2]], [int(z) for z in m[first, 2]]


def hull_mesh(piece: HullObject) -> tuple[np.ndarray, np.ndarray]:
    """A closed surface (world-frame vertices (V, 3), faces (F, 3)) around a hull piece: every column of cells
    filled down to the table (the table hides what is under an object), smoothed, by marching cubes."""
    from skimage.measure import marching_cubes

    lo = piece.cells.min(axis=0)
    lo[2] = 0  # down to the table
    local = piece.cells - lo
    dims = local.max(axis=0) + 1
    solid = np.zeros(tuple(dims), bool)
    solid[local[:, 0], local[:, 1], local[:, 2]] = True
    columns = np.asarray(solid.any(axis=2))
    top = dims[2] - 1 - np.argmax(solid[:, :, ::-1], axis=2)
    zz = np.arange(dims[2])[None, None, :]
    solid |= columns[:, :, None] & (zz <= top[:, :, None])
    padded = ndimage.gaussian_filter(np.pad(solid, 1).astype(np.float32), 0.6)
    verts, faces, _, _ = marching_cubes(padded, level=0.5, spacing=(piece.cell_m,) * 3)
    verts = verts + piece.origin_world + (lo - 1) * piece.cell_m
    verts[:, 2] = np.maximum(verts[:, 2], 0.0)  # the lowest cells' centres stand half a cell above the table
    return verts, faces
