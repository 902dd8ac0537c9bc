"""The clip's camera for `track`: its intrinsics (`clip_camera`: given, or the scan's, `scene_intrinsics`, scaled to
the clip, with the check that their radial distortion does not fold the image, `distortion_folds`), the undistortion
of its frames (`undistorter`), its pose in every frame from the ArUco marker on the table (`marker_camera_poses`), and
the conversions between a pose and OpenCV's rvec, tvec.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from grounder.core.json_files import read_json_file
from grounder.tracking.markers import aligned_grid_px, marker_grid_m, marker_template
from grounder.tracking.options import TrackError, TrackOptions
from grounder.tracking.render import PinholeCamera


def distortion_folds(k1: float, k2: float, image_radius: float) -> bool:
    """Whether OpenCV's radial distortion r_d = r (1 + k1 r^2 + k2 r^4) stops increasing before the distorted radius
    reaches ``image_radius`` (normalised image coordinates): two scene directions would then land on one pixel, and
    no undistortion can tell them apart."""
    radius = np.linspace(0.0, 50.0 * max(image_radius, 1e-6), 200_001)
    slope = 1.0 + 3.0 * k1 * radius**2 + 5.0 * k2 * radius**4
    reached = radius * (1.0 + k1 * radius**2 + k2 * radius**4) >= image_radius
    if not reached.any():  # that radius is never reached: the mapping folds (or shrinks) first
        return True
    return bool((slope[: int(np.argmax(reached)) + 1] <= 0.0).any())


def scene_intrinsics(scene_xml: Path, width_px: int, height_px: int) -> tuple[PinholeCamera, np.ndarray]:
    """The scan's intrinsics, scaled to the clip's size, and OpenCV distortion (k1, k2, 0, 0)."""
    rec_json = scene_xml.parent / "reconstruction" / "reconstruct.json"
    if not rec_json.is_file():
        raise TrackError(
            f"{rec_json} not found: the scene does not say which camera filmed it; pass the clip's intrinsics "
            "(--intrinsics FX FY CX CY)"
        )
    redo = "re-run `image2sim ground` for this scene, or pass the clip's intrinsics (--intrinsics FX FY CX CY)"
    payload = read_json_file(rec_json, redo, TrackError)  # the scene may be someone else's: every value checked
    try:
        intr = payload["intrinsics"]
        keys = ("width_px", "height_px", "fx_px", "fy_px", "cx_px", "cy_px")
        values = [float(intr[k]) for k in keys] + [float(intr.get(k, 0.0)) for k in ("k1", "k2")]
    except (ValueError, KeyError, TypeError, AttributeError, OverflowError) as exc:
        raise TrackError(f"{rec_json}: no readable camera intrinsics ({type(exc).__name__}: {exc}); {redo}") from exc
    if not (np.isfinite(values).all() and min(values[:4]) > 0):
        raise TrackError(
            f"{rec_json}: camera intrinsics {dict(zip(keys, values, strict=False))} are not positive finite numbers; "
            f"{redo}"
        )
    intr = dict(zip((*keys, "k1", "k2"), values, strict=True))
    corner_radius = np.hypot(
        max(intr["cx_px"], intr["width_px"] - intr["cx_px"]) / intr["fx_px"],
        max(intr["cy_px"], intr["height_px"] - intr["cy_px"]) / intr["fy_px"],
    )
    # A fit may bend the model a little past its data at the very corners; folding halfway out is no lens at all.
    if distortion_folds(intr["k1"], intr["k2"], 0.5 * corner_radius):
        raise TrackError(
            f"{rec_json}: distortion k1={intr['k1']:g}, k2={intr['k2']:g} folds the image over less than halfway to "
            f"its corners (no real lens does; frames could not be undistorted); {redo}"
        )
    sx, sy = width_px / intr["width_px"], height_px / intr["height_px"]
    if abs(sx - sy) > 1e-3:
        raise TrackError(
            f"the clip is {width_px}x{height_px} px but the scan was {intr['width_px']}x{intr['height_px']} (another "
            "aspect ratio); pass the clip's intrinsics (--intrinsics FX FY CX CY)"
        )
    camera = PinholeCamera.from_colmap(
        width_px, height_px, intr["fx_px"] * sx, intr["fy_px"] * sy, intr["cx_px"] * sx, intr["cy_px"] * sy
    )
    dist = np.array([intr.get("k1", 0.0), intr.get("k2", 0.0), 0.0, 0.0])
    return camera, dist


def clip_camera(
    scene_xml: Path, width_px: int, height_px: int, options: TrackOptions
) -> tuple[PinholeCamera, np.ndarray]:
    """The clip's pinhole camera and OpenCV distortion: `options.intrinsics_colmap` where given (checked against the
    clip's size; no distortion), else the scan's (`scene_intrinsics`)."""
    if options.intrinsics_colmap is not None:
        fx, fy, cx, cy = options.intrinsics_colmap
        # A focal length outside 0.05-50 image widths is not a camera (a 170-degree fisheye to a 1-degree telephoto);
        # 1e300 px made OpenCV's pose solver fail an assertion.
        focal_ok = all(0.05 * width_px <= f <= 50.0 * width_px for f in (fx, fy))
        if not (np.isfinite([fx, fy, cx, cy]).all() and focal_ok and 0 < cx < width_px and 0 < cy < height_px):
            raise TrackError(
                f"intrinsics fx {fx:g}, fy {fy:g}, cx {cx:g}, cy {cy:g} do not fit the {width_px}x{height_px} clip;"
                f" pass focal lengths of {0.05 * width_px:g}-{50 * width_px:g} px and a principal point inside the "
                "image, in pixels (COLMAP's PINHOLE)"
            )
        camera = PinholeCamera.from_colmap(width_px, height_px, fx, fy, cx, cy)
        dist = np.zeros(4)
    else:
        camera, dist = scene_intrinsics(scene_xml, width_px, height_px)
    return camera, dist


def undistorter(
    camera: PinholeCamera, dist: np.ndarray, width_px: int, height_px: int
) -> Callable[[np.ndarray], np.ndarray]:
    """Undistortion of a clip-sized image with `dist` (k1, k2, 0, 0), keeping `camera`'s matrix; the identity where
    there is no distortion."""
    maps = None
    if np.abs(dist).max() > 0:
        maps = cv2.initUndistortRectifyMap(
            camera.cv_matrix, dist, None, camera.cv_matrix, (width_px, height_px), cv2.CV_32FC1
        )

    def undistort(image: np.ndarray) -> np.ndarray:
        return image if maps is None else cv2.remap(image, maps[0], maps[1], cv2.INTER_LINEAR)

    return undistort


# ---------------------------------------------------------------- camera pose


def marker_camera_poses(
    frames_gray: list[np.ndarray], camera: PinholeCamera, options: TrackOptions
) -> tuple[np.ndarray, bool]:
    """Per-frame `world_from_cam` (F, 4, 4) from the ArUco marker (NaN where unseen), and whether it is static.

    The marker is detected, then its whole image is aligned (ECC homography); the pose is PnP on an 8 x 8 grid of
    marker-plane points. A static camera uses the median grid over up to 30 frames.
    """
    from reconstruction import aruco_detector, detect_marker_corners_px

    if options.aruco_size_m is None:
        raise TrackError("the camera pose comes from the ArUco marker on the table: pass its size (--aruco-size M)")
    detector = aruco_detector(options.aruco_dictionary)
    corners: list[np.ndarray | None] = []
    for gray in frames_gray:
        found = detect_marker_corners_px(gray, detector, options.aruco_id)
        corners.append(None if found is None else found - 0.5)  # COLMAP -> OpenCV pixel convention
    seen = [f for f, c in enumerate(corners) if c is not None]
    if not seen:
        raise TrackError(
            f"ArUco marker {options.aruco_dictionary} id {options.aruco_id} not found in any frame of the clip; "
            "keep the marker of the scan in view"
        )
    seen_corners = [c for c in corners if c is not None]
    median = np.median(np.stack(seen_corners), axis=0)
    spread_px = float(np.median([np.abs(c - median).max() for c in seen_corners]))
    size_m = options.aruco_size_m
    static = options.static_camera if options.static_camera is not None else spread_px < 1.0
    template, px_per_m = marker_template(options.aruco_dictionary, options.aruco_id, size_m)
    grid_m = marker_grid_m(size_m)
    object_points = np.concatenate([grid_m, np.zeros((len(grid_m), 1))], axis=1)

    def grid(f: int) -> np.ndarray | None:
        found = corners[f]
        if found is None:
            return None
        return aligned_grid_px(frames_gray[f], found, template, px_per_m, grid_m, size_m)

    def pose(image_points: np.ndarray) -> np.ndarray:
        ok, rvec, tvec = cv2.solvePnP(object_points, image_points, camera.cv_matrix, None, flags=cv2.SOLVEPNP_SQPNP)
        if not ok:
            return np.full((4, 4), np.nan)
        rvec, tvec = cv2.solvePnPRefineLM(object_points, image_points, camera.cv_matrix, None, rvec, tvec)
        return np.linalg.inv(_pose_from_rt(rvec, tvec))

    if static:
        picks = seen[:: max(1, len(seen) // 30)]
        grids = [g for g in (grid(f) for f in picks) if g is not None]
        if not grids:
            raise TrackError("the marker was detected but its image could not be aligned; is it sharp and flat?")
        return np.repeat(pose(np.median(np.stack(grids), axis=0))[None], len(frames_gray), axis=0), True
    poses = []
    for f in range(len(frames_gray)):
        g = grid(f)
        poses.append(np.full((4, 4), np.nan) if g is None else pose(g))
    return np.stack(poses), False


# ---------------------------------------------------------------- OpenCV poses


def _pose_from_rt(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3] = cv2.Rodrigues(rvec)[0]
    pose[:3, 3] = np.asarray(tvec).ravel()
    return pose


def _rt_from_pose(pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return cv2.Rodrigues(pose[:3, :3])[0], pose[:3, 3].reshape(3, 1).copy()
