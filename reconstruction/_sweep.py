"""Multi-view plane-sweep depth for photo sets: depth at wide, arbitrary baselines, on the CPU.

Rectified two-view stereo (`_dense`) needs a partner displaced mostly sideways by 8-25% of the distance. A video
orbit gives every frame one; 20-40 stills taken from anywhere around a table rarely do (family photo sets paired
5 of 26 frames, and the fused surface held almost nothing). Here each reference view is matched against a few
neighbours 6-40 deg away in any direction: fronto-parallel planes and planes parallel to the table are swept
through the region of interest, each neighbour is warped onto the reference by the plane's homography (OpenCV), and
the windowed normalised
cross-correlation of the best half of the neighbours scores each depth (the other half may be occluded). The
best-scoring depth, refined by a parabola through its neighbours in the sweep, is kept where the score is high
and the window textured; then only depths that another reference's depth map confirms survive (COLMAP's
geometric consistency, in its simplest form).

Pixel coordinates follow OpenCV (first pixel centre at (0, 0)); images arrive undistorted.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True, kw_only=True)
class SweepOptions:
    """Plane-sweep settings.

    Attributes:
        num_planes: fronto-parallel planes, spaced evenly in inverse depth over the region of interest.
        table_planes: planes parallel to the table, spaced evenly over the region's height (0: none).
        max_neighbours: neighbours matched against each reference.
        neighbour_angle_deg: accepted angle between the reference and neighbour rays to the region's centre.
        window_px: side of the NCC window.
        min_ncc: a depth is kept where the aggregated NCC reaches this.
        min_texture: a window needs at least this grey-level standard deviation (0-255) to be matched.
        consistency_rel: two depth maps agree on a point when their depths differ by less than this fraction.
        min_agreeing: other references' depth maps that must agree with a depth for it to be kept.
    """

    num_planes: int = 128
    table_planes: int = 96
    max_neighbours: int = 4
    neighbour_angle_deg: tuple[float, float] = (6.0, 40.0)
    window_px: int = 7
    min_ncc: float = 0.6
    min_texture: float = 4.0
    consistency_rel: float = 0.01
    min_agreeing: int = 1


def choose_neighbours(
    world_from_cams: list[np.ndarray], target_world: np.ndarray, options: SweepOptions
) -> list[list[int]]:
    """Per view, the views whose ray to `target_world` makes an angle in ``neighbour_angle_deg`` with its own and
    which look the same way, nearest to 20 deg first."""
    centres = np.array([t[:3, 3] for t in world_from_cams])
    looks = np.array([t[:3, 2] for t in world_from_cams])
    rays = target_world - centres
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    angle = np.degrees(np.arccos(np.clip(rays @ rays.T, -1.0, 1.0)))
    lo, hi = options.neighbour_angle_deg
    out = []
    for i in range(len(world_from_cams)):
        ok = (angle[i] >= lo) & (angle[i] <= hi) & (looks @ looks[i] > np.cos(np.radians(hi + 10)))
        ok[i] = False
        candidates = np.flatnonzero(ok)
        order = candidates[np.argsort(np.abs(angle[i, candidates] - 20.0))]
        out.append([int(j) for j in order[: options.max_neighbours]])
    return out


def pixel_points_world(
    us: np.ndarray, vs: np.ndarray, z: np.ndarray, k: np.ndarray, world_from_cam: np.ndarray
) -> np.ndarray:
    """(N, 3) world points of pixels (`us`, `vs`) at camera depths `z`, for a pinhole `k` without skew."""
    rays = np.stack([(us - k[0, 2]) / k[0, 0], (vs - k[1, 2]) / k[1, 1], np.ones_like(z)], 1)
    return np.asarray((rays * z[:, None]) @ world_from_cam[:3, :3].T + world_from_cam[:3, 3])


def _box(image: np.ndarray, window: int) -> np.ndarray:
    return np.asarray(cv2.boxFilter(image, cv2.CV_32F, (window, window), borderType=cv2.BORDER_REFLECT), np.float32)


def sweep_depth(
    ref_gray: np.ndarray,
    ref_world_from_cam: np.ndarray,
    neighbours: list[tuple[np.ndarray, np.ndarray]],
    k: np.ndarray,
    depth_range: tuple[float, float],
    options: SweepOptions,
    height_range: tuple[float, float] | None = None,
    crop: tuple[int, int, int, int] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Depth (along the reference camera's z, 0 where unknown) and its aggregated NCC score, (H, W) float32.

    Two families of planes are swept (Gallup et al., CVPR 2007: sweep along the scene's dominant directions):
    ``num_planes`` fronto-parallel ones, evenly in inverse depth over `depth_range`, and, given `height_range`,
    ``table_planes`` planes parallel to the table (world z = h, evenly over the range), which fit the table, the
    objects' tops and a bowl's floor. Each pixel keeps the best-scoring plane of either family, and a depth
    below the bottom of `height_range` (through the table) is never accepted.

    Args:
        ref_gray: (H, W) float32 undistorted grey reference image.
        ref_world_from_cam: (4, 4) reference pose (OpenCV camera axes).
        neighbours: (grey image, world_from_cam) of each neighbour, undistorted, same size and K.
        k: (3, 3) pinhole intrinsics of every image.
        depth_range: (near, far) of the region of interest along the reference camera's z.
        height_range: (low, high) world z of the region of interest (table top at 0).
        crop: (x0, y0, x1, y1) of the reference measured (the region's image); the rest of the map stays 0.
    """
    full_height, full_width = ref_gray.shape
    window = options.window_px
    x0, y0, x1, y1 = crop if crop is not None else (0, 0, full_width, full_height)
    depth_full = np.zeros((full_height, full_width), np.float32)
    score_full = np.full((full_height, full_width), -1.0, np.float32)
    if not neighbours or x1 - x0 < window or y1 - y0 < window:
        return depth_full, score_full
    ref_gray = np.ascontiguousarray(ref_gray[y0:y1, x0:x1])
    height, width = ref_gray.shape
    k_ref = k.copy()
    k_ref[:2, 2] -= (x0, y0)
    mean_r = _box(ref_gray, window)
    var_r = np.maximum(_box(ref_gray * ref_gray, window) - mean_r * mean_r, 0.0)
    k_inv = np.linalg.inv(k_ref)
    cols, rows = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    rays = np.stack([cols, rows, np.ones_like(cols)], axis=-1) @ k_inv.T  # (H, W, 3), z = 1
    # Planes n . X_cam = d in the reference camera's frame, as (n, d, depth per pixel).
    families: list[list[tuple[np.ndarray, float]]] = []
    families.append(
        [
            (np.array([0.0, 0.0, 1.0]), float(1.0 / q))
            for q in np.linspace(1 / depth_range[0], 1 / depth_range[1], options.num_planes)
        ]
    )
    up_in_cam = ref_world_from_cam[2, :3]  # world z of X_cam is up_in_cam . X_cam + t_z
    t_z = float(ref_world_from_cam[2, 3])
    max_depth = np.full((height, width), np.inf)
    if height_range is not None:
        rise = rays @ up_in_cam  # world z gained per unit of depth along each pixel's ray
        with np.errstate(divide="ignore", invalid="ignore"):
            floor_depth = (height_range[0] - t_z) / rise
        max_depth = np.where((rise < 0) & np.isfinite(floor_depth), floor_depth, np.inf)
        if options.table_planes > 1:
            heights = np.linspace(height_range[0], height_range[1], options.table_planes)
            families.append([(up_in_cam, float(h - t_z)) for h in heights if h < t_z])
    best = np.full((height, width), -np.inf, np.float32)
    best_depth = np.zeros((height, width), np.float32)
    prev_score, prev_depth = np.zeros_like(best), np.zeros_like(best)  # the planes on either side of the best
    next_score, next_depth = np.zeros_like(best), np.zeros_like(best)
    has_prev, has_next = np.zeros((height, width), bool), np.zeros((height, width), bool)
    keep = max(1, (len(neighbours) + 1) // 2)
    cams_from_ref = [np.linalg.inv(world_from_cam) @ ref_world_from_cam for _, world_from_cam in neighbours]
    gray_and_ones = [np.dstack([gray, np.ones_like(gray)]).astype(np.float32) for gray, _ in neighbours]
    per_neighbour = np.empty((len(neighbours), height, width), np.float32)
    for planes in families:
        last_score, last_depth = np.full_like(best, -1.0), np.zeros_like(best)
        just_best = np.zeros((height, width), bool)
        for p, (normal, offset) in enumerate(planes):
            with np.errstate(divide="ignore", invalid="ignore"):
                depth = (offset / (rays @ normal)).astype(np.float32)
            for n, cam_from_ref in enumerate(cams_from_ref):
                rotation, translation = cam_from_ref[:3, :3], cam_from_ref[:3, 3]
                # A point X on the plane satisfies n.X / d = 1, so X_cam = (R + t n^T / d) X.
                homography = k @ (rotation + np.outer(translation, normal) / offset) @ k_inv
                # Grey and coverage in one warp: a NaN border would spread through OpenCV's running box sums.
                warped_pair = cv2.warpPerspective(
                    gray_and_ones[n],
                    homography,
                    (width, height),
                    flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                    borderMode=cv2.BORDER_CONSTANT,
                    borderValue=(0.0, 0.0, 0.0, 0.0),
                )
                warped, inside = warped_pair[..., 0], warped_pair[..., 1] > 0.999
                mean_w = _box(warped, window)
                var_w = _box(warped * warped, window) - mean_w * mean_w
                cov = _box(warped * ref_gray, window) - mean_r * mean_w
                # A flat neighbour window (a blown-out highlight) has no correlation to speak of: its variance is
                # 0 while the covariance keeps float32 rounding, which divided by the floor scored up to 3.9.
                textured = inside & (var_w >= options.min_texture**2)
                ncc = cov / np.sqrt(np.maximum(var_r * var_w, 1e-6))
                per_neighbour[n] = np.where(textured, np.clip(ncc, -1.0, 1.0), -1.0)
            if keep == len(neighbours):
                score = per_neighbour.mean(axis=0)
            else:
                score = -np.partition(-per_neighbour, keep - 1, axis=0)[:keep].mean(axis=0)
            score = np.where(np.isfinite(depth) & (depth > 0) & (depth <= max_depth), score, -1.0).astype(np.float32)
            # Pixels whose best plane was the previous one: this plane closes their parabola.
            next_score = np.where(just_best, score, next_score)
            next_depth = np.where(just_best, depth, next_depth)
            has_next |= just_best
            improved = score > best
            best = np.where(improved, score, best)
            best_depth = np.where(improved, depth, best_depth)
            prev_score = np.where(improved, last_score, prev_score)
            prev_depth = np.where(improved, last_depth, prev_depth)
            has_prev = np.where(improved, p > 0, has_prev)
            has_next &= ~improved
            just_best = improved
            last_score, last_depth = score, depth
    # Sub-plane refinement: a parabola through the best plane's score and those of its two neighbours in its sweep.
    inner = has_prev & has_next & (prev_score > -1.0) & (next_score > -1.0)  # both sides scored, not rejected
    curvature = prev_score - 2 * best + next_score
    concave = inner & (curvature < -1e-6)
    shift = np.where(concave, 0.5 * (prev_score - next_score) / np.where(concave, curvature, -1.0), 0.0)
    refined = best_depth + np.clip(shift, -0.5, 0.5) * 0.5 * (next_depth - prev_depth)
    valid = (
        inner
        & np.isfinite(refined)
        & (refined > 0)
        & (best >= options.min_ncc)
        & (np.sqrt(var_r) >= options.min_texture)
    )
    depth_full[y0:y1, x0:x1] = np.where(valid, refined, 0.0)
    score_full[y0:y1, x0:x1] = np.where(np.isfinite(best), best, -1.0)
    return depth_full, score_full


def consistent(
    depths: list[np.ndarray], world_from_cams: list[np.ndarray], k: np.ndarray, options: SweepOptions
) -> list[np.ndarray]:
    """Each depth map with the depths no other map confirms set to 0: a depth is kept when at least
    ``min_agreeing`` other maps, seeing its point, measure it within ``consistency_rel`` of its depth there."""
    out = []
    for i, depth in enumerate(depths):
        vs, us = np.nonzero(depth > 0)
        if len(vs) == 0:
            out.append(depth)
            continue
        z = depth[vs, us]
        points = pixel_points_world(us, vs, z.astype(np.float64), k, world_from_cams[i])
        agree = np.zeros(len(z), np.int32)
        for j, other in enumerate(depths):
            if j == i:
                continue
            cam_from_world = np.linalg.inv(world_from_cams[j])
            in_cam = points @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
            front = in_cam[:, 2] > 1e-6
            pix = in_cam @ k.T
            u = np.round(pix[:, 0] / np.where(front, pix[:, 2], 1)).astype(np.int64)
            v = np.round(pix[:, 1] / np.where(front, pix[:, 2], 1)).astype(np.int64)
            inside = front & (u >= 0) & (u < other.shape[1]) & (v >= 0) & (v < other.shape[0])
            measured = np.zeros(len(z), np.float32)
            measured[inside] = other[v[inside], u[inside]]
            ok = inside & (measured > 0) & (np.abs(measured - in_cam[:, 2]) < options.consistency_rel * in_cam[:, 2])
            agree += ok
        kept = depth.copy()
        drop = agree < options.min_agreeing
        kept[vs[drop], us[drop]] = 0.0
        out.append(kept)
    return out
