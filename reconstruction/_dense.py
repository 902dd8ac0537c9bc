"""Dense geometry on the CPU: rectified semi-global matching on chosen frame pairs, fused in an Open3D TSDF.

pycolmap's PatchMatch needs CUDA; on a CPU we pair each reference frame with a neighbour at a good baseline
(baseline / depth between 0.08 and 0.25), rectify the pair (OpenCV), match with SGBM and a left-right check, and
integrate the depth maps into a scalable TSDF restricted to the region of interest around the objects. Sizes are
relative to the scene (median camera distance), so an unknown scale works too.

Inside this module pixel coordinates follow OpenCV (first pixel centre at (0, 0)); the COLMAP intrinsics are
shifted by -0.5 px on the way in.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from reconstruction._parallel import ordered_ahead, usable_cores
from reconstruction._sweep import SweepOptions, choose_neighbours, consistent, pixel_points_world, sweep_depth
from reconstruction._types import CameraIntrinsics
from reconstruction.errors import DenseError

log = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class DenseOptions:
    """Dense stereo and fusion settings.

    Attributes:
        num_reference_views: frames used as the left image of a stereo pair (spread over the orbit).
        max_image_size_px: longest side at which stereo runs (downscale for speed).
        baseline_ratio: accepted range of baseline / distance to the region of interest.
        min_pairs: below this many pairs in ``baseline_ratio`` (sparse photo sets), unpaired references look for a
            partner in ``wide_baseline_ratio`` (views within 40 deg instead of 30).
        voxel_fraction: TSDF voxel size as a fraction of the median camera distance (0.0035 * 0.74 m = 2.6 mm).
        trunc_voxels: TSDF truncation distance in voxels.
        sgbm_block_px: SGBM block size.
        lr_max_diff_px: left-right consistency tolerance.
        min_weight: a surface needs this many depth maps agreeing on it.
        refine_window_px: window of the sub-pixel disparity refinement.
        edge_disparity_px: disparity jump (px, over 3x3) that marks an occlusion edge.
        sweep: when fewer than ``min_pairs`` pairs are found (a photo set), every view also gets a multi-view
            plane-sweep depth map (`_sweep`) in place of the wide-baseline pairs; None keeps the wide pairs.
    """

    num_reference_views: int = 44
    max_image_size_px: int = 640
    baseline_ratio: tuple[float, float] = (0.08, 0.25)
    min_pairs: int = 12
    wide_baseline_ratio: tuple[float, float] = (0.25, 0.45)
    voxel_fraction: float = 0.0035
    trunc_voxels: float = 4.0
    sgbm_block_px: int = 5
    lr_max_diff_px: float = 1.0
    min_weight: float = 1.0
    refine_window_px: int = 9
    edge_disparity_px: float = 2.0
    sweep: SweepOptions | None = field(default_factory=SweepOptions)


@dataclass(frozen=True, kw_only=True)
class StereoView:
    """One registered frame for dense stereo."""

    image_bgr: np.ndarray  # (H, W, 3) uint8
    world_from_cam: np.ndarray  # (4, 4) OpenCV camera axes


@dataclass(frozen=True, kw_only=True)
class RegionOfInterest:
    """Axis-aligned box in the world frame in which geometry is fused."""

    min_world: np.ndarray  # (3,)
    max_world: np.ndarray  # (3,)

    def contains(self, points: np.ndarray) -> np.ndarray:
        return np.all((points >= self.min_world) & (points <= self.max_world), axis=-1)


@dataclass(frozen=True, kw_only=True)
class DepthMap:
    """One stereo depth map: z along the (rectified) camera axis, 0 where unknown."""

    depth: np.ndarray  # (H, W) float32, world units
    k: np.ndarray  # (3, 3) OpenCV pixel convention
    world_from_cam: np.ndarray  # (4, 4)


@dataclass(frozen=True, kw_only=True)
class DenseResult:
    """Fused dense surface in the world frame."""

    vertices_world: np.ndarray  # (V, 3) TSDF mesh vertices
    faces: np.ndarray  # (F, 3)
    vertex_rgb: np.ndarray  # (V, 3) uint8
    vertex_normals: np.ndarray  # (V, 3)
    voxel_size: float  # world units (metres when the scale is known)
    num_pairs: int
    depth_maps: tuple[DepthMap, ...] = ()
    tsdf_voxels: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.int64))  # (K, 3) i: centre i*voxel
    tsdf_values: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))  # (K,) in [-1, 1], + in front
    tsdf_weights: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))  # (K,) depth maps fused

    def tsdf_sampler(self) -> Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]:
        """A lookup of the TSDF value and weight at world points (M, 3) (nearest voxel; weight 0 where never
        observed). The voxel index is sorted once, so many lookups stay cheap."""
        keys = _voxel_keys(self.tsdf_voxels)
        order = np.argsort(keys)
        sorted_keys = keys[order]
        values, weights = self.tsdf_values[order], self.tsdf_weights[order]

        def sample(points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            out_values = np.zeros(len(points_world), np.float32)
            out_weights = np.zeros(len(points_world), np.float32)
            if len(sorted_keys) == 0:
                return out_values, out_weights
            query = _voxel_keys(np.round(points_world / self.voxel_size).astype(np.int64))
            pos = np.clip(np.searchsorted(sorted_keys, query), 0, len(sorted_keys) - 1)
            found = sorted_keys[pos] == query
            out_values[found] = values[pos[found]]
            out_weights[found] = weights[pos[found]]
            return out_values, out_weights

        return sample


def _voxel_keys(ijk: np.ndarray) -> np.ndarray:
    shifted = ijk.astype(np.int64) + (1 << 20)
    return (shifted[:, 0] << 42) | (shifted[:, 1] << 21) | shifted[:, 2]


def _opencv_k(intrinsics: CameraIntrinsics, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """K and distortion for OpenCV at an image scaled by `scale`.

    COLMAP puts pixel edges at integers, so scaling maps c -> s c; OpenCV's centres are 0.5 px further left/up.
    """
    k = np.array(
        [
            [intrinsics.fx_px * scale, 0.0, intrinsics.cx_px * scale - 0.5],
            [0.0, intrinsics.fy_px * scale, intrinsics.cy_px * scale - 0.5],
            [0.0, 0.0, 1.0],
        ]
    )
    return k, np.array([intrinsics.k1, intrinsics.k2, 0.0, 0.0, 0.0])


def choose_pairs(views: list[StereoView], target: np.ndarray, options: DenseOptions) -> list[tuple[int, int]]:
    """(left, right) index pairs: each reference frame with the neighbour nearest the ideal baseline ratio.

    A video gives every reference a partner in ``baseline_ratio``. A few stills from anywhere around the table
    (an unordered photo set) lie farther apart: 26 photos gave 9 of 26 references a partner there, and the fused
    surface held no object. When fewer than ``min_pairs`` pairs are found, the references left without one take
    a partner in the wider ``wide_baseline_ratio`` (less precise depth, but depth)."""
    pairs = _narrow_pairs(views, target, options)
    if len(pairs) < options.min_pairs:
        paired = {i for pair in pairs for i in pair}
        pairs += _pairs_in(views, target, options, options.wide_baseline_ratio, 40.0, paired)
    return pairs


def _narrow_pairs(views: list[StereoView], target: np.ndarray, options: DenseOptions) -> list[tuple[int, int]]:
    """The pairs in ``baseline_ratio`` (a video's), each reference frame at most once."""
    return _pairs_in(views, target, options, options.baseline_ratio, 30.0, set())


def _pairs_in(
    views: list[StereoView],
    target: np.ndarray,
    options: DenseOptions,
    baseline_ratio: tuple[float, float],
    max_look_deg: float,
    skip: set[int],
) -> list[tuple[int, int]]:
    centres = np.array([v.world_from_cam[:3, 3] for v in views])
    looks = np.array([v.world_from_cam[:3, 2] for v in views])
    distance = np.linalg.norm(centres - target, axis=1)
    refs = np.unique(np.linspace(0, len(views) - 1, min(options.num_reference_views, len(views))).round().astype(int))
    lo, hi = baseline_ratio
    ideal = np.sqrt(lo * hi)
    pairs = []
    for i in refs:
        if int(i) in skip:
            continue
        ratio = np.linalg.norm(centres - centres[i], axis=1) / distance[i]
        cos_look = looks @ looks[i]
        ok = (ratio >= lo) & (ratio <= hi) & (cos_look > np.cos(np.radians(max_look_deg)))
        ok[i] = False
        if not ok.any():
            continue
        candidates = np.flatnonzero(ok)
        j = int(candidates[np.argmin(np.abs(np.log(ratio[candidates] / ideal)))])
        # Horizontal stereo: the partner must be displaced mostly along the reference camera's x axis.
        offset_cam = views[i].world_from_cam[:3, :3].T @ (centres[j] - centres[i])
        if abs(offset_cam[0]) < 2 * abs(offset_cam[1]) or abs(offset_cam[2]) > 0.35 * np.linalg.norm(offset_cam):
            continue
        pairs.append((int(i), j) if offset_cam[0] > 0 else (j, int(i)))
    return pairs


_PairDepth = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]  # depth, colour image, K, world_from_cam


def _pair_depth(
    left: StereoView,
    right: StereoView,
    k: np.ndarray,
    dist: np.ndarray,
    size: tuple[int, int],
    depth_range: tuple[float, float],
    options: DenseOptions,
) -> _PairDepth | None:
    """Depth (in the rectified left camera), its colour image, its K and its world_from_cam; None if unusable."""
    right_from_left = np.linalg.inv(right.world_from_cam) @ left.world_from_cam
    r1, r2, p1, p2, _, _, _ = cv2.stereoRectify(
        k,
        dist,
        k,
        dist,
        size,
        right_from_left[:3, :3],
        right_from_left[:3, 3:].copy(),
        flags=cv2.CALIB_ZERO_DISPARITY,
        alpha=-1,
    )
    if abs(p2[1, 3]) > abs(p2[0, 3]):
        return None  # vertical rectification: skip rather than transpose
    map_l = cv2.initUndistortRectifyMap(k, dist, r1, p1, size, cv2.CV_32FC1)
    map_r = cv2.initUndistortRectifyMap(k, dist, r2, p2, size, cv2.CV_32FC1)
    img_l = cv2.remap(left.image_bgr, *map_l, cv2.INTER_LINEAR)
    img_r = cv2.remap(right.image_bgr, *map_r, cv2.INTER_LINEAR)
    focal = float(p1[0, 0])
    baseline = float(-p2[0, 3] / p2[0, 0])
    if baseline <= 0:
        return None
    d_min = max(0.0, focal * baseline / depth_range[1])
    d_max = focal * baseline / depth_range[0]
    min_disp = int(np.floor(d_min))
    num_disp = int(np.ceil((d_max - min_disp) / 16.0) * 16)
    num_disp = int(np.clip(num_disp, 16, 256))
    block = options.sgbm_block_px
    log.debug("pair: f=%.1f B=%.4f disparities %d..%d", focal, baseline, min_disp, min_disp + num_disp)
    matcher = cv2.StereoSGBM.create(
        minDisparity=min_disp,
        numDisparities=num_disp,
        blockSize=block,
        P1=8 * 3 * block * block,
        P2=32 * 3 * block * block,
        disp12MaxDiff=-1,
        uniquenessRatio=10,
        speckleWindowSize=100,
        speckleRange=2,
        mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY,
    )
    gray_l = cv2.cvtColor(img_l, cv2.COLOR_BGR2GRAY)
    gray_r = cv2.cvtColor(img_r, cv2.COLOR_BGR2GRAY)
    disp_l = matcher.compute(gray_l, gray_r).astype(np.float32) / 16.0
    right_matcher = cv2.ximgproc.createRightMatcher(matcher)
    disp_r = right_matcher.compute(gray_r, gray_l).astype(np.float32) / 16.0
    # Left-right check: the right image's disparity at the matched pixel must agree.
    height, width = disp_l.shape
    cols = np.arange(width, dtype=np.float32)[None, :] - disp_l
    matched = cv2.remap(
        -disp_r, cols, np.repeat(np.arange(height, dtype=np.float32)[:, None], width, 1), cv2.INTER_NEAREST
    )
    valid = (disp_l > min_disp) & (np.abs(matched - disp_l) <= options.lr_max_diff_px)
    # Rectification leaves black borders: drop pixels that map outside either source image.
    inside = cv2.remap(np.full(left.image_bgr.shape[:2], 255, np.uint8), *map_l, cv2.INTER_NEAREST) > 0
    valid &= cv2.erode(inside.astype(np.uint8), np.ones((7, 7), np.uint8)) > 0
    # Block matching fattens foreground objects by about half a block past their silhouettes; drop a band
    # around disparity discontinuities (other views see those surfaces away from their edges).
    local_range = cv2.dilate(disp_l, np.ones((3, 3), np.uint8)) - cv2.erode(disp_l, np.ones((3, 3), np.uint8))
    edges = (local_range > options.edge_disparity_px) & valid
    band = cv2.dilate(edges.astype(np.uint8), np.ones((block + 2, block + 2), np.uint8)) > 0
    valid &= ~band
    disp = refine_disparity(gray_l, gray_r, disp_l, valid, window_px=options.refine_window_px)
    depth = np.where(valid, focal * baseline / np.maximum(disp, 1e-6), 0.0).astype(np.float32)
    k_rect = p1[:3, :3]
    world_from_rect = left.world_from_cam.copy()
    world_from_rect[:3, :3] = left.world_from_cam[:3, :3] @ r1.T
    return depth, img_l, k_rect, world_from_rect


def refine_disparity(
    gray_l: np.ndarray,
    gray_r: np.ndarray,
    disp: np.ndarray,
    valid: np.ndarray,
    *,
    window_px: int = 9,
    iterations: int = 4,
) -> np.ndarray:
    """Sub-pixel refinement of a disparity field by Lucas-Kanade on the warped right image.

    SGBM's sub-pixel step "pixel-locks" and, on weakly textured slanted surfaces (a table seen obliquely), it
    reads disparities 0.4-1.2 px low, i.e. surfaces 3-8 mm too far at 0.7 m. Warping the right image by the whole
    disparity field and solving L(x) = R(x - d - delta) for delta over a window follows the slant and removes that.

    Args:
        gray_l, gray_r: (H, W) rectified images.
        disp: (H, W) float32 disparity of the left image (xL - xR), px.
        valid: (H, W) bool, pixels with a trusted disparity.
        window_px: side of the square window over which delta is solved.
        iterations: Gauss-Newton steps.

    Returns:
        (H, W) float32 refined disparity (unchanged where invalid or textureless).
    """
    left = gray_l.astype(np.float32)
    right = gray_r.astype(np.float32)
    height, width = disp.shape
    rows = np.repeat(np.arange(height, dtype=np.float32)[:, None], width, axis=1)
    cols = np.repeat(np.arange(width, dtype=np.float32)[None, :], height, axis=0)
    d = np.where(valid, disp, 0.0).astype(np.float32)
    weight = valid.astype(np.float32)
    box = (window_px, window_px)
    for _ in range(iterations):
        warped = cv2.remap(right, cols - d, rows, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        grad = np.asarray(cv2.Sobel(warped, cv2.CV_32F, 1, 0, ksize=3), np.float32) / 8.0
        error = np.asarray(left - warped, np.float32)
        num = cv2.boxFilter(np.asarray(weight * grad * error, np.float32), -1, box, normalize=False)
        den = cv2.boxFilter(np.asarray(weight * grad * grad, np.float32), -1, box, normalize=False)
        textured = den > 1.0 * window_px * window_px
        delta = np.where(textured, -num / np.maximum(den, 1e-6), 0.0)
        d = np.where(valid, d + np.clip(delta, -0.5, 0.5), d).astype(np.float32)
    return d


def camera_distance(views: list[StereoView], roi: RegionOfInterest) -> float:
    """The median distance from the cameras to the centre of `roi` (the scene's scale for sizes and margins)."""
    centres = np.array([v.world_from_cam[:3, 3] for v in views])
    return float(np.median(np.linalg.norm(centres - (roi.min_world + roi.max_world) / 2, axis=1)))


def voxel_size(views: list[StereoView], roi: RegionOfInterest, options: DenseOptions) -> float:
    """The TSDF voxel size: `options.voxel_fraction` of the median camera distance to the centre of `roi`."""
    return options.voxel_fraction * camera_distance(views, roi)


def fuse_views(
    views: list[StereoView],
    intrinsics: CameraIntrinsics,
    roi: RegionOfInterest,
    options: DenseOptions | None = None,
    progress: Callable[[int, int], None] | None = None,
    voxel_m: float | None = None,
) -> DenseResult:
    """Depth maps from stereo pairs fused into a TSDF inside `roi`; returns the fused surface mesh.

    Args:
        views: registered frames with their poses (world frame).
        intrinsics: the shared camera (COLMAP convention).
        roi: box in the world frame to reconstruct (objects plus a margin of table).
        options: settings.
        progress: called as progress(done, total) per stereo pair.
        voxel_m: the TSDF voxel size; by default `voxel_size(views, roi, options)`.
    """
    import open3d as o3d

    options = options or DenseOptions()
    height, width = views[0].image_bgr.shape[:2]
    scale = min(1.0, options.max_image_size_px / max(height, width))
    size = (round(width * scale), round(height * scale))
    if scale < 1.0:
        views = [
            StereoView(
                image_bgr=cv2.resize(v.image_bgr, size, interpolation=cv2.INTER_AREA), world_from_cam=v.world_from_cam
            )
            for v in views
        ]
    k, dist = _opencv_k(intrinsics, scale)
    roi_centre = (roi.min_world + roi.max_world) / 2
    voxel = voxel_m if voxel_m is not None else voxel_size(views, roi, options)
    corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float)
    corners = roi.min_world + corners * (roi.max_world - roi.min_world)
    grid = _tsdf_grid(voxel)
    trunc_multiplier = options.trunc_voxels
    # Enough pairs in the video range: those (what `choose_pairs` returns then). Too few: the sweep's depth maps
    # beside them, or without a sweep, `choose_pairs`' wide-baseline partners.
    pairs = _narrow_pairs(views, roi_centre, options)
    sweeping = len(pairs) < options.min_pairs and options.sweep is not None
    if len(pairs) < options.min_pairs and not sweeping:
        pairs = choose_pairs(views, roi_centre, options)
    used = 0
    depth_maps = []

    def depth_range_of(world_from_cam: np.ndarray) -> tuple[float, float]:
        cam_from_world = np.linalg.inv(world_from_cam)
        depths = (corners @ cam_from_world[:3, :3].T + cam_from_world[:3, 3])[:, 2]
        return (max(1e-3, 0.8 * float(depths.min())), 1.2 * float(depths.max()))

    def roi_crop(world_from_cam: np.ndarray) -> tuple[int, int, int, int] | None:
        """Pixel box (x0, y0, x1, y1) of the region of interest in a view; None when it reaches behind it."""
        cam_from_world = np.linalg.inv(world_from_cam)
        in_cam = corners @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
        if (in_cam[:, 2] <= 1e-6).any():
            return None
        pixels = in_cam[:, :2] / in_cam[:, 2:] * np.diag(k)[:2] + k[:2, 2]
        margin = 8
        x0, y0 = np.clip(np.floor(pixels.min(axis=0)) - margin, 0, size).astype(int)
        x1, y1 = np.clip(np.ceil(pixels.max(axis=0)) + margin, 0, size).astype(int)
        return int(x0), int(y0), int(x1), int(y1)

    def pair_depth(pair: tuple[int, int]) -> _PairDepth | None:
        left, right = views[pair[0]], views[pair[1]]
        return _pair_depth(left, right, k, dist, size, depth_range_of(left.world_from_cam), options)

    def integrate(
        depth: np.ndarray, image: np.ndarray, k_depth: np.ndarray, world_from_depth: np.ndarray, sparse: bool = False
    ) -> None:
        """Fuses one depth map; a `sparse` one (scattered pixels, the sweep's) allocates the blocks its points
        touch: Open3D's depth-image overload looks at every 4th pixel only and can miss all of them."""
        nonlocal used
        depth = np.where(np.isfinite(depth) & (depth > 0), depth, 0.0).astype(np.float32)
        # Keep only depths whose 3D point falls inside the region of interest.
        vs, us = np.nonzero(depth > 0)
        points = pixel_points_world(us, vs, depth[vs, us], k_depth, world_from_depth)
        outside = ~roi.contains(points)
        depth[vs[outside], us[outside]] = 0.0
        if not depth.any():
            return  # nothing of this map lies in the box (Open3D refuses a depth map that touches no voxel)
        depth_max = 2 * depth_range_of(world_from_depth)[1]
        depth_image = o3d.t.geometry.Image(np.ascontiguousarray(depth))
        color_image = o3d.t.geometry.Image(np.ascontiguousarray(image[:, :, ::-1], dtype=np.float32) / 255.0)
        k_tensor = o3d.core.Tensor.from_numpy(np.ascontiguousarray(k_depth, np.float64))
        extrinsic = o3d.core.Tensor.from_numpy(np.ascontiguousarray(np.linalg.inv(world_from_depth)))
        if sparse:
            cloud = o3d.t.geometry.PointCloud(o3d.core.Tensor.from_numpy(points[~outside].astype(np.float32)))
            blocks = grid.compute_unique_block_coordinates(cloud, trunc_multiplier)
        else:
            blocks = grid.compute_unique_block_coordinates(
                depth_image, k_tensor, extrinsic, 1.0, depth_max, trunc_multiplier
            )
        grid.integrate(
            blocks, depth_image, color_image, k_tensor, k_tensor, extrinsic, 1.0, depth_max, trunc_multiplier
        )
        used += 1
        depth_maps.append(DepthMap(depth=depth, k=k_depth, world_from_cam=world_from_depth))

    total = len(pairs) + (len(views) if sweeping else 0)
    # The pairs' stereo is independent and OpenCV releases the GIL: computed a few ahead on the other cores, and
    # fused one by one in pair order, as before (the same TSDF to the bit).
    with ThreadPoolExecutor(max(1, min(max(len(pairs), len(views) if sweeping else 0), usable_cores()))) as pool:
        results = ordered_ahead(pool, pair_depth, pairs, ahead=2 * usable_cores())
        for n, out in enumerate(results):
            if progress:
                progress(n + 1, total)
            if out is not None:
                integrate(*out)
        if sweeping:
            assert options.sweep is not None
            sweep_options = options.sweep
            undistorted = [cv2.undistort(v.image_bgr, k, dist) for v in views]
            grays = [cv2.cvtColor(img, cv2.COLOR_BGR2GRAY).astype(np.float32) for img in undistorted]
            poses = [v.world_from_cam for v in views]
            neighbours = choose_neighbours(poses, roi_centre, sweep_options)

            heights = (float(roi.min_world[2]), float(roi.max_world[2]))

            def view_depth(i: int) -> np.ndarray:
                others = [(grays[j], poses[j]) for j in neighbours[i]]
                near, far = depth_range_of(poses[i])
                # A region reaching behind the camera (a wide one, low cameras) starts at a twentieth of its far
                # side: from 1 mm, all but one or two of the planes, even in inverse depth, lay in front of it.
                depth_range = (max(near, 0.05 * far), far)
                return sweep_depth(
                    grays[i], poses[i], others, k, depth_range, sweep_options, heights, crop=roi_crop(poses[i])
                )[0]

            sweeps = []
            for n, depth in enumerate(ordered_ahead(pool, view_depth, range(len(views)), ahead=2 * usable_cores())):
                if progress:
                    progress(len(pairs) + n + 1, total)
                sweeps.append(depth)
            for i, depth in enumerate(consistent(sweeps, poses, k, sweep_options)):
                integrate(depth, undistorted[i], k, poses[i], sparse=True)
    if used == 0:  # Open3D cannot extract from an empty grid (its hash map refuses zero keys)
        raise DenseError(
            f"no stereo pair of frames measured depth where the objects stand ({total} depth map(s) tried of "
            f"{len(views)} views): the views are too few or too far apart; film more of them, closer together (a "
            "video orbit, or photos every 10-15 deg around the table)"
        )
    return _fused_result(grid, voxel, options.min_weight, used, depth_maps)


def _tsdf_grid(voxel_m: float) -> Any:
    """An empty TSDF of `voxel_m` voxels: Open3D's tensor VoxelBlockGrid (sparse blocks; the TSDF values stay
    accessible for meshing). The legacy ScalableTSDFVolume of open3d 0.20 extracts nothing on this CPU build."""
    import open3d as o3d

    return o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight", "color"),
        attr_dtypes=(o3d.core.float32, o3d.core.float32, o3d.core.float32),
        attr_channels=((1), (1), (3)),  # type: ignore[arg-type]  # the stubs want SizeVector; ints work
        voxel_size=voxel_m,
        block_resolution=8,
        block_count=40000,
        device=o3d.core.Device("CPU:0"),
    )


def _fused_result(grid: Any, voxel_m: float, min_weight: float, used: int, depth_maps: list[DepthMap]) -> DenseResult:
    """The fused surface and the observed TSDF voxels of a filled `grid`, each in an order fixed by the geometry."""
    mesh = grid.extract_triangle_mesh(weight_threshold=min_weight).to_legacy()
    coords, flat = grid.voxel_coordinates_and_flattened_indices()
    flat = flat.numpy()
    weights = grid.attribute("weight").numpy().reshape(-1)[flat]
    observed = weights > 0
    voxel_ijk = np.round(coords.numpy()[observed] / voxel_m).astype(np.int64)
    tsdf_values = grid.attribute("tsdf").numpy().reshape(-1)[flat][observed]
    mesh.compute_vertex_normals()
    vertex_order, faces = canonical_mesh_order(np.asarray(mesh.vertices), np.asarray(mesh.triangles))
    voxel_order = np.argsort(_voxel_keys(voxel_ijk), kind="stable")
    return DenseResult(
        vertices_world=np.asarray(mesh.vertices)[vertex_order],
        faces=faces,
        vertex_rgb=(np.clip(np.asarray(mesh.vertex_colors)[vertex_order], 0, 1) * 255).round().astype(np.uint8),
        vertex_normals=np.asarray(mesh.vertex_normals)[vertex_order],
        voxel_size=voxel_m,
        num_pairs=used,
        depth_maps=tuple(depth_maps),
        tsdf_voxels=voxel_ijk[voxel_order],
        tsdf_values=tsdf_values[voxel_order].astype(np.float32),
        tsdf_weights=weights[observed][voxel_order].astype(np.float32),
    )


def canonical_mesh_order(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A mesh's vertices and faces in an order fixed by its geometry alone: ``(vertex_order, faces)``, where
    ``vertices[vertex_order]`` are sorted by (x, y, z) and ``faces`` index them, each face rotated to start at its
    smallest index (winding kept), faces sorted.

    Open3D's TSDF grid allocates blocks from several threads, so the same fusion lists its surface in a different
    order from run to run. The surface is the same, but everything after it (clustering, the winding-number inside
    test, marching cubes) sums in that order, and on the tabletop sample the bowl came out 0.1% different in volume
    between two runs of one reconstruction.
    """
    vertex_order = np.lexsort(np.asarray(vertices).T[::-1])
    new_index = np.empty(len(vertex_order), np.int64)
    new_index[vertex_order] = np.arange(len(vertex_order))
    remapped = new_index[np.asarray(faces, np.int64)].reshape(-1, 3)
    shift = np.argmin(remapped, axis=1)
    rows = np.arange(len(remapped))[:, None]
    rotated = remapped[rows, (shift[:, None] + np.arange(3)[None, :]) % 3]
    return vertex_order, rotated[np.lexsort(rotated.T[::-1])]
