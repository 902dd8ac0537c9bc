"""From SfM's arbitrary similarity frame to a metric, gravity-aligned world frame.

- Gravity is the normal of the dominant support plane of the sparse points, pointing towards the cameras.
- With an ArUco marker, its four corners are detected in every registered frame that sees it, triangulated with the
  SfM cameras, and a similarity maps the marker model onto them: that fixes origin, heading and scale. The plane,
  fitted to many more points than the marker's four, fixes the tilt; the origin is put on the plane, so the table
  top is z = 0 and the marker centre is the origin.
- With a known extent, the largest cluster of points above the plane sets the scale.
- Otherwise the scale stays SfM's (unknown) and the caller warns.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import least_squares

from reconstruction._colmap import pycolmap
from reconstruction._types import ScaleSource, WorldFrame
from reconstruction.errors import WorldFrameError

log = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class Plane:
    """Plane n . x + d = 0 with unit normal n (pointing to the side the cameras are on)."""

    normal: np.ndarray
    offset: float
    inliers: np.ndarray  # (N,) bool over the points it was fitted to


# A table plane has every camera above it and few points below it (noise, reflections): at most this share.
MAX_POINTS_BELOW_TABLE = 0.25
# Planes tried, most inliers first, each found among the points the planes before it left (sequential RANSAC).
MAX_PLANES_TRIED = 4


def fit_support_plane(points: np.ndarray, cam_centres: np.ndarray, *, seed: int = 0) -> Plane:
    """The table: the plane with the most points (RANSAC, Open3D, refined by least squares on its inliers) that can
    be a table under the cameras, every camera above it and at most `MAX_POINTS_BELOW_TABLE` of the points below.

    The plane with the most points is not always the table: on a plain table the face of a box or a mix of objects
    carries more points (held-out photo set 1071: 21% of the points on a plane with half of them below it and
    cameras under it; the scene came out tilted 44 deg, its objects fell off the table). Planes are tried in order,
    each among the points the ones before left, up to `MAX_PLANES_TRIED`.

    Args:
        points: (N, 3) sparse points, any consistent frame and unit.
        cam_centres: (M, 3) camera centres in the same frame; the normal is flipped to face them.

    Raises:
        WorldFrameError: too few points, or no plane the cameras can all be above (the reconstruction itself is then
            inconsistent: frames matched wrongly).
    """
    if len(points) < 50:
        raise WorldFrameError(
            f"only {len(points)} 3D points were reconstructed, too few to find the table plane; "
            "film a textured table with more overlap"
        )
    centre = np.median(points, axis=0)
    scene_size = float(np.median(np.linalg.norm(cam_centres - centre, axis=1)))
    threshold = 0.006 * scene_size
    remaining = np.ones(len(points), bool)
    tried: list[tuple[int, float]] = []
    for _ in range(MAX_PLANES_TRIED):
        if remaining.sum() < 50:
            break
        plane = _dominant_plane(points, remaining, cam_centres, threshold, seed)
        cams_below = int(np.sum(cam_centres @ plane.normal + plane.offset < -threshold))
        below = float(np.mean(points @ plane.normal + plane.offset < -threshold))
        if cams_below == 0 and below <= MAX_POINTS_BELOW_TABLE:
            return plane
        tried.append((cams_below, below))
        remaining &= ~plane.inliers
    found = "; ".join(f"{c} camera(s) and {100 * b:.0f}% of the points below" for c, b in tried)
    raise WorldFrameError(
        f"no plane in the {len(points)} reconstructed points can be the table under the cameras ({found}): the "
        "frames were matched inconsistently; film the table with more texture and overlap, or put the ArUco marker "
        "on it (--aruco-size)"
    )


def _dominant_plane(
    points: np.ndarray, among: np.ndarray, cam_centres: np.ndarray, threshold: float, seed: int
) -> Plane:
    """The plane with the most of the points `among` (a mask) within `threshold`, refitted to every point near it,
    its normal towards the median camera."""
    import open3d as o3d

    o3d.utility.random.seed(seed)
    candidates = np.flatnonzero(among)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points[candidates].astype(np.float64)))
    _, inlier_ids = cloud.segment_plane(distance_threshold=threshold, ransac_n=3, num_iterations=2000)
    inliers = np.zeros(len(points), bool)
    inliers[candidates[np.asarray(inlier_ids, int)]] = True
    # Least-squares refit, then re-select inliers at the same threshold, until the inliers stop changing: two rounds
    # left the plane where RANSAC's sample put it (Open3D's RANSAC runs in threads and is not repeatable), and the
    # scale a known extent gives moved by 1% between runs on the same points.
    for _ in range(20):
        on_plane = points[inliers]
        mean = on_plane.mean(axis=0)
        normal = np.linalg.svd(on_plane - mean, full_matrices=False)[2][2]  # not the N x N U: 1.2 s a call
        offset = -float(normal @ mean)
        refit = np.abs(points @ normal + offset) < threshold
        if np.array_equal(refit, inliers):
            break
        inliers = refit
    if np.median(cam_centres @ normal + offset) < 0:
        normal, offset = -normal, -offset
    return Plane(normal=normal, offset=offset, inliers=inliers)


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest rotation taking unit vector a to unit vector b."""
    v = np.cross(a, b)
    c = float(a @ b)
    if np.linalg.norm(v) < 1e-12:
        if c > 0:
            return np.eye(3)
        axis = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
        axis /= np.linalg.norm(axis)
        return 2 * np.outer(axis, axis) - np.eye(3)
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx * (1 / (1 + c))


def umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity (s, R, t) minimising sum |s R src_i + t - dst_i|^2 (Umeyama 1991)."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    u, sing, vt = np.linalg.svd(cov)
    sign = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sign[2, 2] = -1
    rot = u @ sign @ vt
    scale = float(np.trace(np.diag(sing) @ sign) / (xs**2).sum(1).mean())
    return scale, rot, mu_d - scale * rot @ mu_s


def similarity_matrix(scale: float, rot: np.ndarray, trans: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = scale * rot
    out[:3, 3] = trans
    return out


# ---------------------------------------------------------------- ArUco


def aruco_detector(dictionary_name: str) -> cv2.aruco.ArucoDetector:
    if not hasattr(cv2.aruco, dictionary_name):
        raise WorldFrameError(f"unknown ArUco dictionary {dictionary_name!r}; use one of cv2.aruco's DICT_* names")
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    params.cornerRefinementWinSize = 4
    params.cornerRefinementMaxIterations = 60
    params.cornerRefinementMinAccuracy = 0.01
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary_name))
    return cv2.aruco.ArucoDetector(dictionary, params)


def detect_marker_corners_px(
    image_bgr: np.ndarray, detector: cv2.aruco.ArucoDetector, marker_id: int
) -> np.ndarray | None:
    """(4, 2) corners of the marker in COLMAP pixel convention (upper-left pixel centre at (0.5, 0.5)).

    Order (OpenCV's): the marker image's top-left, top-right, bottom-right, bottom-left.
    """
    corners, ids, _ = detector.detectMarkers(image_bgr)
    if ids is None:
        return None
    hits = [c for c, i in zip(corners, ids.ravel(), strict=True) if i == marker_id]
    if len(hits) != 1:
        return None
    gray = cv2.cvtColor(image_bgr, cv2.COLOR_BGR2GRAY) if image_bgr.ndim == 3 else image_bgr
    refined = refine_corners_by_edges(gray.astype(np.float32), hits[0].reshape(4, 2).astype(np.float64))
    if refined is None:
        return None
    return refined + 0.5  # OpenCV puts the first pixel centre at (0, 0); COLMAP at (0.5, 0.5)


def refine_corners_by_edges(
    gray: np.ndarray, corners: np.ndarray, *, search_px: float = 4.0, iterations: int = 3
) -> np.ndarray | None:
    """Corners as intersections of lines fitted to the marker's four edges.

    Corner detectors (cornerSubPix) pull the corner of a blurred dark square inwards by about half a pixel,
    which biases the metric scale by ~1% for a marker 100 px wide. The 50% crossing of a blurred straight edge
    is unbiased, so we locate it along each side's normal at many stations, fit a line, and intersect.

    Args:
        gray: (H, W) float32 image, OpenCV pixel convention.
        corners: (4, 2) initial corners in OpenCV's order (clockwise in the image).

    Returns:
        (4, 2) refined corners in OpenCV pixel convention, or None if an edge could not be measured.
    """
    current = corners
    for _ in range(iterations):  # each pass samples the edge profile around better lines
        refined = _refine_once(gray, current, search_px)
        if refined is None or np.max(np.linalg.norm(refined - corners, axis=1)) > search_px:
            return None
        if np.max(np.linalg.norm(refined - current, axis=1)) < 0.01:
            return refined
        current = refined
    return current


def _refine_once(gray: np.ndarray, corners: np.ndarray, search_px: float) -> np.ndarray | None:
    centre = corners.mean(axis=0)
    lines = []
    offsets = np.linspace(-search_px, search_px, int(search_px * 8) + 1)
    for k in range(4):
        a, b = corners[k], corners[(k + 1) % 4]
        along = (b - a) / np.linalg.norm(b - a)
        normal = np.array([-along[1], along[0]])
        if normal @ ((a + b) / 2 - centre) < 0:
            normal = -normal  # points outwards, from the black border to the white margin
        length = float(np.linalg.norm(b - a))
        stations = a + np.outer(np.linspace(0.12, 0.88, max(8, int(length / 2))) * length, along)
        samples = stations[:, None, :] + offsets[None, :, None] * normal[None, None, :]
        profile = cv2.remap(
            gray, samples[..., 0].astype(np.float32), samples[..., 1].astype(np.float32), cv2.INTER_LINEAR
        )
        edge_points = []
        for station, values in zip(stations, profile, strict=True):
            dark, bright = float(values[:5].mean()), float(values[-5:].mean())
            if bright - dark < 20.0:
                continue
            level = (dark + bright) / 2
            above = np.flatnonzero(values >= level)
            if len(above) == 0 or above[0] == 0:
                continue
            j = above[0]  # first crossing from the dark side
            frac = (level - values[j - 1]) / (values[j] - values[j - 1])
            edge_points.append(station + (offsets[j - 1] + frac * (offsets[j] - offsets[j - 1])) * normal)
        if len(edge_points) < 5:
            return None
        pts = np.asarray(edge_points)
        mean = pts.mean(axis=0)
        direction = np.linalg.svd(pts - mean)[2][0]
        lines.append((mean, direction))
    refined = np.zeros((4, 2))
    for k in range(4):
        (p0, d0), (p1, d1) = lines[(k - 1) % 4], lines[k]  # corner k joins side k-1 and side k
        t = np.linalg.solve(np.stack([d0, -d1], axis=1), p1 - p0)
        refined[k] = p0 + t[0] * d0
    return refined


def marker_corners_marker_frame(size_m: float) -> np.ndarray:
    """(4, 3) corners in the marker frame (x right, y up), in OpenCV's detection order."""
    h = size_m / 2
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


def triangulate_point(rays_cam: list[np.ndarray], cams_from_world: list[np.ndarray]) -> np.ndarray:
    """Multi-view triangulation: linear (DLT on normalised image coordinates), then reprojection refinement.

    Args:
        rays_cam: per view (2,) normalised image coordinates (x/z, y/z) after undistortion.
        cams_from_world: per view (3, 4) [R | t].
    """
    rows = []
    for xy, pose in zip(rays_cam, cams_from_world, strict=True):
        rows.append(xy[0] * pose[2] - pose[0])
        rows.append(xy[1] * pose[2] - pose[1])
    point_h = np.linalg.svd(np.asarray(rows))[2][-1]
    point = point_h[:3] / point_h[3]

    def residuals(p: np.ndarray) -> np.ndarray:
        out = []
        for xy, pose in zip(rays_cam, cams_from_world, strict=True):
            q = pose[:, :3] @ p + pose[:, 3]
            out.append(q[:2] / q[2] - xy)
        return np.concatenate(out)

    return least_squares(residuals, point, loss="soft_l1", f_scale=2e-3).x


@dataclass(frozen=True, kw_only=True)
class MarkerObservation:
    image_name: str
    corners_px: np.ndarray  # (4, 2) COLMAP pixel convention


def triangulate_marker(rec: pycolmap.Reconstruction, observations: list[MarkerObservation]) -> tuple[np.ndarray, float]:
    """Marker corners in the SfM frame, (4, 3), and their reprojection RMS in pixels."""
    by_name = {image.name: image for image in rec.images.values() if image.has_pose}
    used = [o for o in observations if o.image_name in by_name]
    if len(used) < 2:
        raise WorldFrameError(
            f"the ArUco marker was found in {len(used)} registered frame(s) but at least 2 are needed; "
            "keep the whole marker (with its white margin) in view for part of the orbit"
        )
    poses = [by_name[o.image_name].cam_from_world().matrix() for o in used]
    cameras = [by_name[o.image_name].camera for o in used]
    corners = np.zeros((4, 3))
    sq_errors = []
    for k in range(4):
        rays = [cam.cam_from_img(o.corners_px[k : k + 1])[0] for cam, o in zip(cameras, used, strict=True)]
        corners[k] = triangulate_point(rays, poses)
        for cam, pose, o in zip(cameras, poses, used, strict=True):
            proj = cam.img_from_cam((pose[:, :3] @ corners[k] + pose[:, 3])[None])[0]
            sq_errors.append(float(np.sum((proj - o.corners_px[k]) ** 2)))
    return corners, float(np.sqrt(np.mean(sq_errors)))


# ---------------------------------------------------------------- world frames


def _frame_on_plane(plane: Plane, origin_sfm: np.ndarray, x_hint_sfm: np.ndarray, scale: float) -> np.ndarray:
    """world_from_sfm with z = plane normal, origin = origin_sfm projected onto the plane, x along x_hint."""
    z = plane.normal
    origin = origin_sfm - (origin_sfm @ z + plane.offset) * z
    x = x_hint_sfm - (x_hint_sfm @ z) * z
    if np.linalg.norm(x) < 1e-9:
        raise WorldFrameError("could not choose a heading: the reference direction is parallel to gravity")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    world_r_sfm = np.stack([x, y, z])  # rows: world axes expressed in SfM coordinates
    return similarity_matrix(scale, world_r_sfm, -scale * world_r_sfm @ origin)


def world_from_marker(
    rec: pycolmap.Reconstruction, plane: Plane, observations: list[MarkerObservation], size_m: float
) -> WorldFrame:
    corners_sfm, rms_px = triangulate_marker(rec, observations)
    model = marker_corners_marker_frame(size_m)
    scale, rot, trans = umeyama(corners_sfm, model)  # marker model <- sfm
    residual_m = float(np.sqrt(np.mean(np.sum((scale * corners_sfm @ rot.T + trans - model) ** 2, axis=1))))
    if residual_m > 0.05 * size_m:
        raise WorldFrameError(
            f"the triangulated marker is not a {size_m} m square (fit residual {residual_m * 1000:.1f} mm); "
            "check --aruco-size and that the marker lies flat"
        )
    # Heading from the marker's x axis (in SfM coordinates), tilt from the plane, origin at the marker centre.
    x_hint_sfm = rot.T @ np.array([1.0, 0.0, 0.0])
    marker_normal_sfm = rot.T @ np.array([0.0, 0.0, 1.0])
    tilt_deg = float(np.rad2deg(np.arccos(np.clip(marker_normal_sfm @ plane.normal, -1, 1))))
    notes = [f"marker normal is {tilt_deg:.2f} deg from the support plane normal"]
    if tilt_deg > 5:
        raise WorldFrameError(f"the marker is tilted {tilt_deg:.1f} deg from the table plane; lay it flat on the table")
    world_from_sfm = _frame_on_plane(plane, corners_sfm.mean(axis=0), x_hint_sfm, scale)
    return WorldFrame(
        world_from_sfm=world_from_sfm,
        scale_source=ScaleSource.ARUCO,
        scale=scale,
        plane_inlier_ratio=float(plane.inliers.mean()),
        marker_views=len(observations),
        marker_corner_rms_px=rms_px,
        notes=tuple(notes),
    )


def objects_above_plane(
    points: np.ndarray, plane: Plane, scene_size: float, min_cluster_points: int = 15
) -> list[np.ndarray]:
    """Clusters of at least `min_cluster_points` points clearly above the plane (DBSCAN in Open3D), largest
    first, as index arrays."""
    import open3d as o3d

    height = points @ plane.normal + plane.offset
    above = np.flatnonzero((height > 0.012 * scene_size) & (height < 0.6 * scene_size))
    if len(above) < 10:
        return []
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points[above].astype(np.float64)))
    labels = np.asarray(cloud.cluster_dbscan(eps=0.04 * scene_size, min_points=8))
    clusters = [above[labels == k] for k in range(labels.max() + 1)]
    clusters = [c for c in clusters if len(c) >= min_cluster_points]
    return sorted(clusters, key=len, reverse=True)


def footprint_extents(points: np.ndarray, plane: Plane, x_hint: np.ndarray) -> np.ndarray:
    """(3,) robust extents of a cluster: along its footprint's principal axes in the plane, and its height.

    Sparse SfM points include strays that would inflate a bounding rectangle by 20-40%; statistical outlier
    removal followed by 1st-99th percentile spans recovers the true extents within a few percent.
    """
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64)))
    _, keep = cloud.remove_statistical_outlier(nb_neighbors=20, std_ratio=2.0)
    if len(keep) >= 10:
        points = points[np.asarray(keep, int)]
    z = plane.normal
    x = x_hint - (x_hint @ z) * z
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    uv = np.stack([points @ x, points @ y], axis=1)
    uv -= np.median(uv, axis=0)
    axes = np.linalg.eigh(np.cov(uv.T))[1]
    along = uv @ axes
    spans = np.percentile(along, 99, axis=0) - np.percentile(along, 1, axis=0)
    top = float(np.percentile(points @ z + plane.offset, 98))
    return np.array([spans[0], spans[1], top])


NOMINAL_CAMERA_DISTANCE_M = 0.6  # a provisional scale puts the cameras this far from the table's centre


def world_from_extent(
    rec: pycolmap.Reconstruction,
    plane: Plane,
    points: np.ndarray,
    cam_centres: np.ndarray,
    extent_m: float,
    *,
    provisional_ok: bool = False,
) -> WorldFrame:
    """The world frame scaled so that the largest cluster of points above the table spans `extent_m`; with
    `provisional_ok` and no such cluster (a plain object gives SfM no points), a provisional scale that puts the
    cameras `NOMINAL_CAMERA_DISTANCE_M` from the table's centre, for the caller to correct on the meshes."""
    scene_size = float(np.median(np.linalg.norm(cam_centres - np.median(points, 0), axis=1)))
    clusters = objects_above_plane(points, plane, scene_size)
    if not clusters and provisional_ok:
        centre = _table_centre(points, plane)
        scale = NOMINAL_CAMERA_DISTANCE_M / float(np.median(np.linalg.norm(cam_centres - centre, axis=1)))
        return WorldFrame(
            world_from_sfm=_frame_on_plane(plane, centre, _first_camera_x(rec), scale),
            scale_source=ScaleSource.KNOWN_EXTENT,
            scale=scale,
            plane_inlier_ratio=float(plane.inliers.mean()),
            notes=(
                "no cluster of points stands above the plane: provisional scale (cameras "
                f"{NOMINAL_CAMERA_DISTANCE_M} m from the table's centre) until the known extent is measured on a mesh",
            ),
            scale_provisional=True,
        )
    if not clusters:
        raise WorldFrameError(
            "--known-extent needs an object on the table, but no cluster of points stands above the table "
            "plane; film the object from more sides or use --aruco-size with a marker"
        )
    x_hint = _first_camera_x(rec)
    extents = [footprint_extents(points[c], plane, x_hint) for c in clusters]
    largest = int(np.argmax([e.max() for e in extents]))
    longest_sfm = float(extents[largest].max())
    scale = extent_m / longest_sfm
    origin = points[clusters[largest]].mean(axis=0)
    return WorldFrame(
        world_from_sfm=_frame_on_plane(plane, origin, x_hint, scale),
        scale_source=ScaleSource.KNOWN_EXTENT,
        scale=scale,
        plane_inlier_ratio=float(plane.inliers.mean()),
        notes=(
            f"{len(clusters)} object cluster(s) above the plane; the largest spans "
            f"{np.round(extents[largest] * scale, 4).tolist()} m (longest set to {extent_m} m); origin below it",
        ),
    )


def world_unknown_scale(rec: pycolmap.Reconstruction, plane: Plane, points: np.ndarray) -> WorldFrame:
    return WorldFrame(
        world_from_sfm=_frame_on_plane(plane, _table_centre(points, plane), _first_camera_x(rec), 1.0),
        scale_source=ScaleSource.UNKNOWN,
        scale=1.0,
        plane_inlier_ratio=float(plane.inliers.mean()),
        notes=("scale unknown: units are SfM units, not metres",),
    )


def _table_centre(points: np.ndarray, plane: Plane) -> np.ndarray:
    """The origin of a frame with no object to stand under: the mean of the table's points (SfM coordinates)."""
    return np.asarray(points[plane.inliers].mean(axis=0))


def _first_camera_x(rec: pycolmap.Reconstruction) -> np.ndarray:
    first = min((im for im in rec.images.values() if im.has_pose), key=lambda im: im.name)
    return first.cam_from_world().rotation.matrix()[0]  # camera x axis in SfM coordinates
