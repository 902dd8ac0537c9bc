"""ArUco markers for `track`: the table marker's image alignment, and optional markers stuck on objects.

**Alignment** (table and object markers alike): the marker is detected (OpenCV ArUco), then its whole image (black
square, bits and a white quiet zone of 1/8 of its side) is aligned to the frame by an ECC homography, and the pose
comes from PnP on an 8 x 8 grid of marker-plane points. On the toss sample the four detected corners alone gave
the camera 4 mm / 0.25 deg off; the aligned image halves both. On a 4.8 cm marker 30 px wide (the box of
`samples/toss_markers`) the corners refined along the edges gave 1.9 mm / 1.3 deg, and with a quiet zone narrower
than the edge search (5 mm) they were 33 mm off along the ray.

**Object markers** (`--object-markers FILE`): a marker printed with a white border at least 1/8 of its side, stuck
on an object after the scan. In every frame that shows it, it gives the object's pose independently of the mesh's
texture and silhouette. Layout file (JSON)::

    {"markers": [{"id": 1, "size_m": 0.048},
                 {"id": 2, "size_m": 0.036, "object": "can", "pos_m": [0, 0, 0.0553], "quat_wxyz": [1, 0, 0, 0]}]}

- `id`: the marker's id in the dictionary (`TrackOptions.aruco_dictionary`), not the table marker's;
- `size_m`: side of its black square, metres;
- `object` (optional): the grounded object carrying it (`scene.json`); without it, the object whose tracked motion
  the marker follows;
- `pos_m`, `quat_wxyz` (optional, together): the marker frame in the object's body frame. Marker frame: origin at
  the square's centre, x along its top edge (from the marker image's top-left corner to its top-right), y from its
  bottom edge to its top, z out of the printed face. A grounded scene's body frame is its mesh's bounding box, which
  a user does not know: without them the marker is *placed* from the frames where both it and the object's
  model-based track are seen (the robust mean of the marker pose in the object's frame).

A small square seen at an angle has two poses that reproject almost alike (the planar solver returns both, tilted
opposite ways); the one nearer the object's model-based orientation is taken, or, where there is none, the better
one only if the other reprojects `ambiguity_ratio` times worse.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from grounder.core.json_files import read_json_file
from grounder.errors import GrounderError, shown
from grounder.tracking.render import PinholeCamera
from image2sim_common.progress import ProgressFn, no_progress
from image2sim_common.rotations import pose_matrix, quat_from_matrix, rotation_angle_deg

log = logging.getLogger(__name__)

MARKER_TEMPLATE_PX = 120  # black square side in the ECC template
MARKER_QUIET_ZONE = 0.125  # white border around the black square used for ECC, as a fraction of its side
MARKER_GRID = 8  # marker-plane points per side used for the pose
MIN_ECC = 0.8  # an aligned marker image must correlate at least this well with the frame


# ---------------------------------------------------------------- alignment (table and object markers)


def marker_template(dictionary: str, marker_id: int, size_m: float) -> tuple[np.ndarray, float]:
    """The marker's image (black square, bits, a white quiet zone), slightly blurred, and its pixels per metre."""
    aruco_dict = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    image = cv2.aruco.generateImageMarker(aruco_dict, marker_id, MARKER_TEMPLATE_PX)
    border = round(MARKER_QUIET_ZONE * MARKER_TEMPLATE_PX)
    image = cv2.copyMakeBorder(image, border, border, border, border, cv2.BORDER_CONSTANT, value=255)
    return cv2.GaussianBlur(image.astype(np.float32), (0, 0), 2.0), MARKER_TEMPLATE_PX / size_m


def marker_grid_m(size_m: float) -> np.ndarray:
    """(G, 2) marker-plane points (x right, y up, metres) spanning the square and its quiet zone."""
    half = size_m * (0.5 + MARKER_QUIET_ZONE / 2)
    axis = np.linspace(-half, half, MARKER_GRID)
    return np.array([[x, y] for y in axis for x in axis])


def _template_px(points_marker_m: np.ndarray, template: np.ndarray, px_per_m: float) -> np.ndarray:
    """Marker-plane points (N, 2) (x right, y up, metres) -> template pixels (OpenCV convention)."""
    centre = template.shape[0] / 2 - 0.5
    return np.stack([centre + points_marker_m[:, 0] * px_per_m, centre - points_marker_m[:, 1] * px_per_m], axis=1)


def aligned_grid_px(
    gray: np.ndarray,
    corners_px: np.ndarray,
    template: np.ndarray,
    px_per_m: float,
    grid_m: np.ndarray,
    size_m: float,
    *,
    min_ecc: float = 0.0,
) -> np.ndarray | None:
    """Where the marker-plane grid points fall in the frame, from an ECC homography fit of the marker's image
    started at the detected corners (OpenCV pixel convention). None where ECC fails or correlates below min_ecc."""
    from reconstruction import marker_corners_marker_frame

    warp = cv2.getPerspectiveTransform(
        _template_px(marker_corners_marker_frame(size_m)[:, :2], template, px_per_m).astype(np.float32),
        corners_px.astype(np.float32),
    )
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-6)
    try:
        everywhere = np.full(gray.shape, 255, np.uint8)
        ecc, warp = cv2.findTransformECC(
            template, gray.astype(np.float32), warp.astype(np.float32), cv2.MOTION_HOMOGRAPHY, criteria, everywhere, 1
        )
    except cv2.error:
        return None
    if ecc < min_ecc:
        return None
    grid_px = _template_px(grid_m, template, px_per_m)[None].astype(np.float32)
    return np.asarray(cv2.perspectiveTransform(grid_px, warp)[0], np.float64)


# ---------------------------------------------------------------- object markers: layout


@dataclass(frozen=True, kw_only=True)
class ObjectMarker:
    """One ArUco marker on one object.

    Attributes:
        marker_id: the marker's id in the dictionary.
        size_m: side of its black square, metres.
        object_name: the grounded object's name, or None to find it from the clip.
        body_from_marker: (4, 4) the marker frame in the object's body frame, or None to place it from the clip.
        origin: where the place came from: "layout" (a `--object-markers` file) or "scan" (`scene.json`, measured
            by `ground`).
    """

    marker_id: int
    size_m: float
    object_name: str | None = None
    body_from_marker: np.ndarray | None = None
    origin: str = "layout"


def _marker_id(value: object) -> int:
    """A marker id from a JSON value: a whole number (2 or 2.0; not 2.9, which `int` would make 2, nor a bool)."""
    if isinstance(value, bool) or not isinstance(value, int | float) or not float(value).is_integer():
        raise ValueError(f"id must be a whole number, got {shown(value)}")
    return int(value)


def _marker_from_row(row: object, where: str, origin: str) -> ObjectMarker:
    """One layout entry (module docstring) -> ObjectMarker; GrounderError, one line, on anything malformed."""
    if not isinstance(row, dict):
        raise GrounderError(f"{where}: expected an object with id and size_m")
    try:
        marker_id, size_m = _marker_id(row["id"]), float(row["size_m"])
        name = None if row.get("object") is None else str(row["object"])
    except (KeyError, TypeError, ValueError) as exc:
        raise GrounderError(f"{where}: needs id and size_m (optionally object, pos_m, quat_wxyz): {exc}") from exc
    if not 0.0 < size_m < 1.0:
        raise GrounderError(f"{where}: size_m={size_m} but expected the square's side in metres, e.g. 0.05")
    body_from_marker = None
    if "pos_m" in row or "quat_wxyz" in row:
        try:
            pos = np.asarray(row["pos_m"], dtype=np.float64)
            quat = np.asarray(row.get("quat_wxyz", [1.0, 0.0, 0.0, 0.0]), dtype=np.float64)
        except (KeyError, TypeError, ValueError) as exc:
            raise GrounderError(f"{where}: pos_m must be 3 numbers and quat_wxyz 4: {exc}") from exc
        if pos.shape != (3,) or quat.shape != (4,) or not (np.isfinite(pos).all() and np.isfinite(quat).all()):
            raise GrounderError(f"{where}: pos_m must be 3 numbers and quat_wxyz 4")
        if abs(np.linalg.norm(quat) - 1.0) > 1e-3:
            raise GrounderError(f"{where}: quat_wxyz has norm {np.linalg.norm(quat):.4f}; give a unit quaternion")
        if name is None:
            raise GrounderError(f"{where}: pos_m is in an object's body frame; name the object too")
        body_from_marker = pose_matrix(pos, quat)
    return ObjectMarker(
        marker_id=marker_id, size_m=size_m, object_name=name, body_from_marker=body_from_marker, origin=origin
    )


def load_object_markers(path: Path) -> tuple[ObjectMarker, ...]:
    """The markers of a layout file (module docstring). Raises GrounderError, one line, on anything malformed."""
    path = Path(path)
    payload = read_json_file(path, "pass a marker layout (JSON) as docs/cli.md documents it")
    rows = payload.get("markers") if isinstance(payload, dict) else None
    if not isinstance(rows, list) or not rows:
        raise GrounderError(f'{path}: expected {{"markers": [...]}} with at least one marker')
    markers = tuple(_marker_from_row(row, f"{path}: marker {k}", "layout") for k, row in enumerate(rows))
    ids = [m.marker_id for m in markers]
    if len(set(ids)) != len(ids):
        raise GrounderError(f"{path}: marker ids {ids} repeat; each marker needs its own id")
    return markers


def scene_markers(scene_json: Path) -> tuple[ObjectMarker, ...]:
    """The object markers `ground` measured in the scan (`scene.json` `object_markers`); none if it has none."""
    path = Path(scene_json)
    if not path.is_file():
        return ()
    manifest = read_json_file(path, "ground the scene again")
    if not isinstance(manifest, dict):
        raise GrounderError(f"{path}: expected a JSON object, not {shown(manifest)}; ground the scene again")
    rows = manifest.get("object_markers") or []
    if not isinstance(rows, list):
        raise GrounderError(
            f"{path}: 'object_markers' is {type(rows).__name__} {shown(rows)}, not a list of markers; ground the "
            "scene again"
        )
    return tuple(_marker_from_row(row, f"{path}: object marker {k}", "scan") for k, row in enumerate(rows))


def combined_markers(layout: Sequence[ObjectMarker], scan: Sequence[ObjectMarker]) -> tuple[ObjectMarker, ...]:
    """The layout's markers, then the scan's whose ids the layout does not give (a layout entry overrides)."""
    given = {m.marker_id for m in layout}
    return (*layout, *(m for m in scan if m.marker_id not in given))


def check_markers(
    markers: Sequence[ObjectMarker], object_names: Sequence[str], dictionary: str, table_marker_id: int
) -> None:
    """Raises GrounderError if a marker names an object the scene lacks, reuses the table marker's id, or has an id
    outside the dictionary."""
    size = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary)).bytesList.shape[0]
    for m in markers:
        if m.object_name is not None and m.object_name not in object_names:
            raise GrounderError(
                f"marker {m.marker_id} is on {m.object_name!r}, but the scene's objects are {list(object_names)}"
            )
        if m.marker_id == table_marker_id:
            raise GrounderError(f"marker {m.marker_id} has the table marker's id; object markers need other ids")
        if not 0 <= m.marker_id < size:
            raise GrounderError(f"marker id {m.marker_id} is not in {dictionary} (ids 0-{size - 1})")


# ---------------------------------------------------------------- object markers: measurement


@dataclass(frozen=True, kw_only=True)
class MarkerViews:
    """Every object marker's two candidate poses per frame (the planar ambiguity), better-reprojecting first.

    Attributes:
        world_from_marker: (F, M, 2, 4, 4) NaN where the marker is not seen (or its second solution is missing).
        rms_px: (F, M, 2) RMS reprojection error of the grid points, pixels (NaN where missing).
    """

    world_from_marker: np.ndarray
    rms_px: np.ndarray

    @property
    def seen(self) -> np.ndarray:
        """(F, M) the marker was detected and aligned."""
        return np.isfinite(self.rms_px[:, :, 0])

    def unambiguous(self, ratio: float) -> np.ndarray:
        """(F, M) seen, and the second solution reprojects at least `ratio` times worse (or there is none)."""
        second = np.where(np.isfinite(self.rms_px[:, :, 1]), self.rms_px[:, :, 1], np.inf)
        return self.seen & (second >= ratio * self.rms_px[:, :, 0])


def measure_markers(
    grays: Sequence[np.ndarray],
    camera: PinholeCamera,
    world_from_cam: np.ndarray,
    markers: Sequence[ObjectMarker],
    dictionary: str,
    *,
    progress: ProgressFn | None = None,
) -> MarkerViews:
    """Detects and aligns every object marker in every frame with a known camera pose; both planar solutions."""
    from reconstruction import aruco_detector

    report = progress or no_progress
    detector = aruco_detector(dictionary)
    slot = {m.marker_id: k for k, m in enumerate(markers)}
    templates = [marker_template(dictionary, m.marker_id, m.size_m) for m in markers]
    grids = [marker_grid_m(m.size_m) for m in markers]
    object_points = [np.concatenate([grid, np.zeros((len(grid), 1))], axis=1) for grid in grids]
    frames, count = len(grays), len(markers)
    poses = np.full((frames, count, 2, 4, 4), np.nan)
    rms = np.full((frames, count, 2), np.nan)
    for f, gray in enumerate(grays):
        report("object markers", f, frames)
        if not np.isfinite(world_from_cam[f]).all():
            continue
        corners, ids, _ = detector.detectMarkers(gray)
        if ids is None:
            continue
        for found, marker_id in zip(corners, ids.ravel(), strict=True):
            k = slot.get(int(marker_id))
            if k is None:
                continue
            template, px_per_m = templates[k]
            grid_m = grids[k]
            image_px = aligned_grid_px(
                gray, found.reshape(4, 2), template, px_per_m, grid_m, markers[k].size_m, min_ecc=MIN_ECC
            )
            if image_px is None:
                continue
            points = object_points[k]
            solutions, rvecs, tvecs, _ = cv2.solvePnPGeneric(
                points, image_px, camera.cv_matrix, None, flags=cv2.SOLVEPNP_IPPE
            )
            for s in range(min(int(solutions), 2)):
                rvec, tvec = cv2.solvePnPRefineLM(points, image_px, camera.cv_matrix, None, rvecs[s], tvecs[s])
                residual = cv2.projectPoints(points, rvec, tvec, camera.cv_matrix, None)[0].reshape(-1, 2)
                cam_from_marker = np.eye(4)
                cam_from_marker[:3, :3] = cv2.Rodrigues(rvec)[0]
                cam_from_marker[:3, 3] = np.ravel(tvec)
                poses[f, k, s] = world_from_cam[f] @ cam_from_marker
                rms[f, k, s] = float(np.sqrt(np.mean(np.sum((residual - image_px) ** 2, axis=1))))
            if np.isfinite(rms[f, k]).all() and rms[f, k, 1] < rms[f, k, 0]:
                poses[f, k] = poses[f, k, ::-1].copy()
                rms[f, k] = rms[f, k, ::-1].copy()
    report("object markers", frames, frames)
    return MarkerViews(world_from_marker=poses, rms_px=rms)


# ---------------------------------------------------------------- object markers: placement


@dataclass(frozen=True, kw_only=True)
class MarkerPlacement:
    """Where a marker was found to sit (or was said to sit).

    Attributes:
        marker_id: the marker.
        object_name: the object carrying it (None: the marker is not used; `note` says why).
        frames: frames the placement was measured on (0 where the layout gave it).
        spread_mm, spread_p90_mm, spread_deg: median / 90th percentile of the distances, and median angle, of
            those frames' marker poses in the object frame from the placement (NaN where the layout gave it).
        given: the layout gave the placement.
        note: why a marker is not used.
    """

    marker_id: int
    object_name: str | None
    frames: int
    spread_mm: float = float("nan")
    spread_p90_mm: float = float("nan")
    spread_deg: float = float("nan")
    given: bool = False
    note: str = ""


def _robust_mean_pose(
    samples: np.ndarray, *, trim_m: float, trim_deg: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The mean of (S, 4, 4) poses after dropping those farther than trim (or 3 median deviations) from the median;
    and every sample's distance (m) and angle (deg) from it."""
    centre = np.median(samples[:, :3, 3], axis=0)
    rotation = samples[int(np.argmin(np.linalg.norm(samples[:, :3, 3] - centre, axis=1))), :3, :3]
    for _ in range(2):
        dist = np.linalg.norm(samples[:, :3, 3] - centre, axis=1)
        angle = np.array([rotation_angle_deg(rotation, s[:3, :3]) for s in samples])
        keep = (dist <= max(trim_m, 3.0 * np.median(dist))) & (angle <= max(trim_deg, 3.0 * np.median(angle)))
        kept = samples[keep] if keep.any() else samples
        centre = kept[:, :3, 3].mean(axis=0)
        u, _, vt = np.linalg.svd(kept[:, :3, :3].sum(axis=0))  # chordal mean of the rotations
        rotation = u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt
    out = np.eye(4)
    out[:3, :3] = rotation
    out[:3, 3] = centre
    dist = np.linalg.norm(samples[:, :3, 3] - centre, axis=1)
    angle = np.array([rotation_angle_deg(rotation, s[:3, :3]) for s in samples])
    return out, dist, angle


def place_markers(
    views: MarkerViews,
    markers: Sequence[ObjectMarker],
    object_names: Sequence[str],
    world_from_objects: np.ndarray,
    valid: np.ndarray,
    *,
    ambiguity_ratio: float,
    max_spread_m: float,
    min_frames: int = 5,
) -> tuple[tuple[ObjectMarker, ...], tuple[MarkerPlacement, ...]]:
    """Fills in each marker's object and place from the frames where it and a model-based track are both seen.

    For a candidate object, each such frame (unambiguous marker poses only) gives the marker's pose in the object's
    frame: inverse object pose times marker pose. A marker on the object gives nearly the same pose in every frame;
    a marker on another object does not, but only in the frames where the two move apart, which may be few (objects
    rest most of a clip). So the marker goes to the object with the smallest 90th percentile of the deviations from
    the robust mean pose, if that is at most `max_spread_m`, and is placed at that mean. A marker no tracked object
    follows is not used (logged).

    Returns:
        The markers with object and body_from_marker set (those not placed keep None), and what was found.
    """
    placed: list[ObjectMarker] = []
    report: list[MarkerPlacement] = []
    clear = views.unambiguous(ambiguity_ratio)
    names = list(object_names)
    for k, marker in enumerate(markers):
        if marker.body_from_marker is not None:
            placed.append(marker)
            report.append(
                MarkerPlacement(marker_id=marker.marker_id, object_name=marker.object_name, frames=0, given=True)
            )
            continue
        fits: list[MarkerPlacement] = []
        poses: list[np.ndarray] = []
        for name in [marker.object_name] if marker.object_name is not None else names:
            i = names.index(name)
            frames = np.nonzero(clear[:, k] & valid[:, i])[0]
            if len(frames) < min_frames:
                continue
            samples = np.stack(
                [np.linalg.inv(world_from_objects[f, i]) @ views.world_from_marker[f, k, 0] for f in frames]
            )
            pose, dist_m, angle_deg = _robust_mean_pose(samples, trim_m=0.003, trim_deg=3.0)
            poses.append(pose)
            fits.append(
                MarkerPlacement(
                    marker_id=marker.marker_id,
                    object_name=name,
                    frames=len(frames),
                    spread_mm=1e3 * float(np.median(dist_m)),
                    spread_p90_mm=1e3 * float(np.percentile(dist_m, 90)),
                    spread_deg=float(np.median(angle_deg)),
                )
            )
        best = min(range(len(fits)), key=lambda j: fits[j].spread_p90_mm, default=None)
        if best is None or fits[best].spread_p90_mm > 1e3 * max_spread_m:
            why = (
                f"fewer than {min_frames} frames show it and a tracked object"
                if best is None
                else f"no tracked object moves with it (nearest: {fits[best].object_name}, 90% of frames within "
                f"{fits[best].spread_p90_mm:.1f} mm, more than {1e3 * max_spread_m:.0f} mm)"
            )
            log.warning("object marker %d is not used: %s", marker.marker_id, why)
            placed.append(marker)
            report.append(
                MarkerPlacement(marker_id=marker.marker_id, object_name=None, frames=0, note=why)
                if best is None
                else replace(fits[best], object_name=None, note=why)
            )
            continue
        fit = fits[best]
        log.info(
            "object marker %d is on %s (placed from %d frames; 90%% within %.1f mm)",
            marker.marker_id,
            fit.object_name,
            fit.frames,
            fit.spread_p90_mm,
        )
        placed.append(replace(marker, object_name=fit.object_name, body_from_marker=poses[best]))
        report.append(fit)
    return tuple(placed), tuple(report)


# ---------------------------------------------------------------- object markers: poses


@dataclass(frozen=True, kw_only=True)
class MarkerPoses:
    """Object poses measured by their markers.

    Attributes:
        world_from_objects: (F, N, 4, 4) where `seen`, else NaN.
        seen: (F, N) a marker of the object was seen and its pose accepted.
        rms_px: (F, N) RMS grid reprojection error of the accepted pose (NaN where not seen).
    """

    world_from_objects: np.ndarray
    seen: np.ndarray
    rms_px: np.ndarray


def marker_object_poses(
    views: MarkerViews,
    markers: Sequence[ObjectMarker],
    object_names: Sequence[str],
    *,
    reference: np.ndarray | None = None,
    ambiguity_ratio: float = 3.0,
    max_rms_px: float = 0.5,
) -> MarkerPoses:
    """Per frame and object, the pose its placed marker gives (the best-reprojecting where it carries several).

    Args:
        views: `measure_markers`' output for these markers.
        markers: placed markers (`place_markers`); unplaced ones are skipped.
        reference: (F, N, 4, 4) object poses (e.g. the model-based track) to choose between the two planar
            solutions, NaN where none; without one only unambiguous frames are used.
        ambiguity_ratio: with no reference, the other solution must reproject this many times worse.
        max_rms_px: a pose whose grid reprojects worse than this (RMS) is not used.
    """
    frames, count = views.rms_px.shape[0], len(object_names)
    poses = np.full((frames, count, 4, 4), np.nan)
    error = np.full((frames, count), np.nan)
    clear = views.unambiguous(ambiguity_ratio)
    for k, marker in enumerate(markers):
        if marker.object_name is None or marker.body_from_marker is None:
            continue
        i = list(object_names).index(marker.object_name)
        marker_from_body = np.linalg.inv(marker.body_from_marker)
        for f in np.nonzero(views.seen[:, k])[0]:
            candidates = [
                (float(views.rms_px[f, k, s]), views.world_from_marker[f, k, s] @ marker_from_body)
                for s in range(2)
                if np.isfinite(views.rms_px[f, k, s])
            ]
            ref = None if reference is None else reference[f, i]
            if ref is not None and np.isfinite(ref).all():
                rms_px, pose = min(candidates, key=lambda c: rotation_angle_deg(ref[:3, :3], c[1][:3, :3]))
            elif clear[f, k]:
                rms_px, pose = candidates[0]
            else:
                continue
            if rms_px > max_rms_px or (np.isfinite(error[f, i]) and rms_px >= error[f, i]):
                continue
            poses[f, i] = pose
            error[f, i] = rms_px
    return MarkerPoses(world_from_objects=poses, seen=np.isfinite(error), rms_px=error)


def marker_agreement(
    measured: MarkerPoses, world_from_objects: np.ndarray, model_based: np.ndarray, world_from_cam: np.ndarray
) -> list[tuple[int, float, float]]:
    """Per object, how far its marker-measured poses lie from its model-based track where both exist: (frames,
    median distance across the camera ray in mm, median angle in deg); (0, NaN, NaN) where they never overlap.

    Only the distance across the ray counts: along it the model-based track is off by up to 15 mm before the depth
    correction from the table (the box of `samples/toss_markers`), which is applied afterwards. A marker whose given
    place is wrong (moved after the scan, a layout typo) shows as a steady offset across the ray or in angle.
    """
    out = []
    for i in range(measured.seen.shape[1]):
        frames = np.nonzero(measured.seen[:, i] & model_based[:, i])[0]
        if not len(frames):
            out.append((0, float("nan"), float("nan")))
            continue
        marker, model = measured.world_from_objects[frames, i], world_from_objects[frames, i]
        ray = model[:, :3, 3] - world_from_cam[frames, :3, 3]
        ray /= np.linalg.norm(ray, axis=1, keepdims=True)
        offset = marker[:, :3, 3] - model[:, :3, 3]
        across = offset - np.sum(offset * ray, axis=1, keepdims=True) * ray
        angle_deg = [rotation_angle_deg(a[:3, :3], b[:3, :3]) for a, b in zip(marker, model, strict=True)]
        out.append((len(frames), 1e3 * float(np.median(np.linalg.norm(across, axis=1))), float(np.median(angle_deg))))
    return out


def placement_json(
    marker: ObjectMarker, placement: MarkerPlacement, agreement: tuple[int, float, float] | None = None
) -> dict[str, object]:
    """One marker's record for `track.json`: the layout entry it would take, how it was placed, and (`agreement`)
    how its object's marker poses compare with the model-based track."""
    out: dict[str, object] = {
        "id": marker.marker_id,
        "size_m": marker.size_m,
        "object": placement.object_name,
        "placed_by": marker.origin if placement.given else "clip",
        "placed_from_frames": placement.frames,
    }
    if marker.body_from_marker is not None and placement.object_name is not None:
        out["pos_m"] = np.round(marker.body_from_marker[:3, 3], 6).tolist()
        out["quat_wxyz"] = np.round(quat_from_matrix(marker.body_from_marker[:3, :3]), 6).tolist()
    for key in ("spread_mm", "spread_p90_mm", "spread_deg"):
        value = getattr(placement, key)
        if np.isfinite(value):
            out[key] = round(float(value), 3)
    if agreement is not None and agreement[0]:
        out["model_agreement"] = {
            "frames": agreement[0],
            "median_across_ray_mm": round(agreement[1], 2),
            "median_deg": round(agreement[2], 2),
        }
    if placement.note:
        out["note"] = placement.note
    return out
