"""Object markers measured in the scan: ArUco markers stuck on objects before scanning are found by `ground`.

Stick a printed marker (the table marker's dictionary, another id, a white border at least 1/8 of its side) on an
object before filming the scan, and `ground` measures it: in every registered scan frame the marker's corners are
detected and refined along its edges (`reconstruction._world.refine_corners_by_edges`), each corner is triangulated
from all views with the SfM cameras, a square is fitted to the four corners (its side is measured, not asked for),
and the marker goes to the object whose bounding box it lies on (within `max_distance_m`). Its pose in that object's
body frame goes to `scene.json` (`object_markers`), where `track` finds it: a marker measured this way needs no
layout file, and its place is as exact as the scan's cameras (the grounded body frame is the mesh's bounding box,
which a user cannot measure by hand).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from image2sim_common.rotations import quat_from_matrix
from reconstruction import CameraIntrinsics, TextureView

log = logging.getLogger(__name__)


def _cv_matrix(intr: CameraIntrinsics) -> np.ndarray:
    """K in OpenCV's pixel convention (upper-left pixel centre at 0, 0)."""
    return np.array([[intr.fx_px, 0.0, intr.cx_px - 0.5], [0.0, intr.fy_px, intr.cy_px - 0.5], [0.0, 0.0, 1.0]])


def _distortion(intr: CameraIntrinsics) -> np.ndarray:
    return np.array([intr.k1, intr.k2, 0.0, 0.0])


@dataclass(frozen=True, kw_only=True)
class ScanMarker:
    """A marker found on an object in the scan.

    Attributes:
        marker_id: its id.
        object_name: the body it sits on.
        size_m: side of its black square as triangulated.
        body_from_marker: (4, 4) the marker frame (centre of the square; x along its top edge; y up the image; z out
            of the face) in the body frame.
        views: scan frames it was measured in.
        rms_px: corner reprojection RMS over those views.
        distance_m: distance of its centre from the object's bounding box (0 inside).
    """

    marker_id: int
    object_name: str
    size_m: float
    body_from_marker: np.ndarray
    views: int
    rms_px: float
    distance_m: float

    def to_json(self) -> dict[str, object]:
        """The entry `scene.json` stores (and a `--object-markers` layout takes)."""
        return {
            "id": self.marker_id,
            "object": self.object_name,
            "size_m": round(self.size_m, 6),
            "pos_m": np.round(self.body_from_marker[:3, 3], 6).tolist(),
            "quat_wxyz": np.round(quat_from_matrix(self.body_from_marker[:3, :3]), 7).tolist(),
            "views": self.views,
            "rms_px": round(self.rms_px, 3),
            "distance_to_object_m": round(self.distance_m, 4),
        }


def _detect(views: Sequence[TextureView], dictionary: str, skip_id: int) -> dict[int, list[tuple[int, np.ndarray]]]:
    """Per marker id (other than skip_id): (view index, (4, 2) corners in OpenCV pixels), the corners from aligning
    the marker's whole image (`aligned_grid_px`, as `track` does), which a thin white border does not bias."""
    from grounder.tracking.markers import MIN_ECC, aligned_grid_px, marker_template
    from reconstruction import aruco_detector, marker_corners_marker_frame

    detector = aruco_detector(dictionary)
    templates: dict[int, tuple[np.ndarray, float]] = {}
    unit_corners_m = marker_corners_marker_frame(1.0)[
        :, :2
    ]  # the template is in units of the marker's side: any size will do
    found: dict[int, list[tuple[int, np.ndarray]]] = {}
    for v, view in enumerate(views):
        gray = cv2.cvtColor(view.image_bgr, cv2.COLOR_BGR2GRAY)
        corners, ids, _ = detector.detectMarkers(gray)
        if ids is None:
            continue
        for quad, marker_id in zip(corners, ids.ravel(), strict=True):
            if int(marker_id) == skip_id:
                continue
            if int(marker_id) not in templates:
                templates[int(marker_id)] = marker_template(dictionary, int(marker_id), 1.0)
            template, px_per_m = templates[int(marker_id)]
            aligned = aligned_grid_px(
                gray, quad.reshape(4, 2), template, px_per_m, unit_corners_m, 1.0, min_ecc=MIN_ECC
            )
            if aligned is not None:
                found.setdefault(int(marker_id), []).append((v, aligned))
    return found


def _triangulate(views: Sequence[TextureView], seen: list[tuple[int, np.ndarray]]) -> tuple[np.ndarray, float, int]:
    """(4, 3) world corners triangulated from the views that saw them, their reprojection RMS in pixels, and the
    number of views used: a view whose corners reproject more than 3x the median error (and 0.5 px) off is dropped
    once and the rest triangulated again (a grazing view whose corners the edge refinement pulled)."""
    from reconstruction import triangulate_point

    def solve(used: list[tuple[int, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
        cams_from_world = [np.linalg.inv(views[v].world_from_cam)[:3] for v, _ in used]
        rays = [
            cv2.undistortPoints(
                px.reshape(-1, 1, 2), _cv_matrix(views[v].intrinsics), _distortion(views[v].intrinsics)
            ).reshape(4, 2)
            for v, px in used
        ]
        corners = np.stack([triangulate_point([r[k] for r in rays], cams_from_world) for k in range(4)])
        errors = []
        for (v, px), cam_from_world in zip(used, cams_from_world, strict=True):
            in_cam = corners @ cam_from_world[:, :3].T + cam_from_world[:, 3]
            zero = np.zeros(3)
            projected = cv2.projectPoints(
                in_cam, zero, zero, _cv_matrix(views[v].intrinsics), _distortion(views[v].intrinsics)
            )[0]
            errors.append(float(np.sqrt(np.mean(np.sum((projected.reshape(4, 2) - px) ** 2, axis=1)))))
        return corners, np.array(errors)

    corners, errors = solve(seen)
    keep = errors <= max(0.5, 3.0 * float(np.median(errors)))
    if not keep.all() and keep.sum() >= 2:
        seen = [s for s, k in zip(seen, keep, strict=True) if k]
        corners, errors = solve(seen)
    return corners, float(np.sqrt(np.mean(errors**2))), len(seen)


def _square_pose(corners_world: np.ndarray) -> tuple[np.ndarray, float, float]:
    """world_from_marker of the square best fitting four corners (OpenCV's order), its side, and the RMS residual."""
    from reconstruction import marker_corners_marker_frame, umeyama

    unit = marker_corners_marker_frame(1.0)
    size_m, rot, trans = umeyama(unit, corners_world)
    pose = np.eye(4)
    pose[:3, :3] = rot
    pose[:3, 3] = trans
    residual = corners_world - (size_m * unit @ rot.T + trans)
    return pose, size_m, float(np.sqrt(np.mean(np.sum(residual**2, axis=1))))


def _box_distance(point_body: np.ndarray, extents_m: np.ndarray) -> float:
    return float(np.linalg.norm(np.maximum(np.abs(point_body) - np.asarray(extents_m) / 2, 0.0)))


def find_scan_markers(
    views: Sequence[TextureView],
    bodies: Mapping[str, tuple[np.ndarray, np.ndarray]],
    dictionary: str,
    table_marker_id: int,
    *,
    min_views: int = 3,
    max_rms_px: float = 1.5,
    max_distance_m: float = 0.01,
) -> tuple[tuple[ScanMarker, ...], tuple[str, ...]]:
    """Every object marker of the scan, placed on its object; and a note for each marker seen but not placed.

    Args:
        views: registered scan frames.
        bodies: per body name, (world_from_body (4, 4) at the scan, extents_m (3,) of its bounding box).
        dictionary: the ArUco dictionary (the table marker's).
        table_marker_id: the table marker's id (not an object marker).
        min_views: views needed to triangulate a marker.
        max_rms_px: larger corner reprojection RMS: the detections do not agree (a marker moved, or two alike).
        max_distance_m: a marker farther than this from every object's bounding box is on none.
    """
    markers: list[ScanMarker] = []
    notes: list[str] = []
    for marker_id, seen in sorted(_detect(views, dictionary, table_marker_id).items()):
        if len(seen) < min_views:
            notes.append(f"object marker {marker_id}: seen in {len(seen)} scan frame(s), {min_views} needed")
            continue
        corners, rms_px, used = _triangulate(views, seen)
        world_from_marker, size_m, residual_m = _square_pose(corners)
        if rms_px > max_rms_px or residual_m > 0.05 * size_m:
            notes.append(
                f"object marker {marker_id}: its corners do not triangulate to one square ({rms_px:.2f} px, "
                f"{1e3 * residual_m:.1f} mm off); was it moved during the scan?"
            )
            continue
        distances = {
            name: _box_distance((np.linalg.inv(pose) @ world_from_marker)[:3, 3], extents)
            for name, (pose, extents) in bodies.items()
        }
        name = min(distances, key=lambda n: distances[n], default=None)
        if name is None or distances[name] > max_distance_m:
            notes.append(f"object marker {marker_id}: not on any object (centre {corners.mean(axis=0).round(3)} m)")
            continue
        body_from_marker = np.linalg.inv(bodies[name][0]) @ world_from_marker
        markers.append(
            ScanMarker(
                marker_id=marker_id,
                object_name=name,
                size_m=size_m,
                body_from_marker=body_from_marker,
                views=used,
                rms_px=rms_px,
                distance_m=distances[name],
            )
        )
        log.info(
            "object marker %d on %s: %.1f mm square from %d scan frames (%.2f px)",
            marker_id,
            name,
            1e3 * size_m,
            used,
            rms_px,
        )
    for note in notes:
        log.warning(note)
    return tuple(markers), tuple(notes)
