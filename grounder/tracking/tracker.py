"""The model-based pose search of `track`, frame by frame: render-and-compare refinement of every tracked object
(`_Tracker.refine`: masked ZNCC, then Lucas-Kanade from the rendering into the frame and PnP), SIFT detection where
an object is not tracked (`_Tracker.detect`), the checks a pose must pass (`_accept`: agreeing features,
appearance, in the image, out of the table, near where its motion puts it), the forward pass over the clip
(`track_frames`), the backward pass into the frames before each track and the trimming of a run's edge frames next to
a gap; with the image helpers they use (`normalise`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import cv2
import numpy as np

from grounder.tracking.camera import _pose_from_rt, _rt_from_pose
from grounder.tracking.options import FrameScore, TrackError, TrackOptions
from grounder.tracking.output import iter_valid_runs
from grounder.tracking.render import (
    FeatureModel,
    PoseRenderer,
    RenderedView,
    ScanFrame,
    backproject,
    build_feature_models,
    merged_feature_models,
    scan_feature_models,
)
from grounder.tracking.support import StaticGeometry
from image2sim_common.progress import ProgressFn, no_progress
from image2sim_common.rotations import matrix_from_quat, rotation_angle_deg

log = logging.getLogger(__name__)

GRAVITY_M_S2 = 9.81


# ---------------------------------------------------------------- image helpers


def normalise(gray: np.ndarray, sigma_px: float = 4.0) -> np.ndarray:
    """Local contrast normalisation (subtract the local mean, divide by the local deviation) as uint8 for LK."""
    g = gray.astype(np.float32)
    mean = cv2.GaussianBlur(g, (0, 0), sigma_px)
    centred = g - mean
    std = np.sqrt(cv2.GaussianBlur(centred * centred, (0, 0), sigma_px)) + 4.0
    return np.clip(128.0 + 40.0 * centred / std, 0, 255).astype(np.uint8)


def _zncc(a: np.ndarray, b: np.ndarray) -> float:
    a = a.astype(np.float64) - a.mean()
    b = b.astype(np.float64) - b.mean()
    denom = float(np.sqrt((a * a).sum() * (b * b).sum()))
    return float((a * b).sum() / denom) if denom > 0 else 0.0


def _template_shift(rend_norm: np.ndarray, real_norm: np.ndarray, mask: np.ndarray, search_px: int) -> np.ndarray:
    """Image shift (dx, dy) of the rendered object that best matches the frame within +-search_px (masked ZNCC).

    Gives Lucas-Kanade a start when the prediction is far off (first frames, impacts); zero when nothing matches.
    """
    rows, cols = np.nonzero(mask)
    if len(rows) == 0:
        return np.zeros(2)
    y0, y1, x0, x1 = rows.min(), rows.max() + 1, cols.min(), cols.max() + 1
    height, width = real_norm.shape
    ry0, ry1 = max(0, y0 - search_px), min(height, y1 + search_px)
    rx0, rx1 = max(0, x0 - search_px), min(width, x1 + search_px)
    template = rend_norm[y0:y1, x0:x1].astype(np.float32) - 128.0
    region = real_norm[ry0:ry1, rx0:rx1].astype(np.float32) - 128.0
    if region.shape[0] < template.shape[0] or region.shape[1] < template.shape[1]:
        return np.zeros(2)
    weights = mask[y0:y1, x0:x1].astype(np.float32)
    score = cv2.matchTemplate(region, template * weights, cv2.TM_CCORR_NORMED, mask=weights)
    score = np.nan_to_num(score, nan=-1.0, posinf=-1.0, neginf=-1.0)
    _, best, _, (bx, by) = cv2.minMaxLoc(score)
    if best < 0.3:
        return np.zeros(2)
    return np.array([rx0 + bx - x0, ry0 + by - y0], np.float64)


# ---------------------------------------------------------------- the tracker


@dataclass
class _Step:
    pose: np.ndarray | None
    inliers: int = 0
    followed: int = 0
    ncc: float = float("nan")
    reason: str = ""

    def score(self, in_frame: float, *, source: str = "lost", reason: str = "") -> FrameScore:
        """This step's support as a frame's score: accepted (`source`) or rejected (`reason`)."""
        return FrameScore(
            inliers=self.inliers,
            inlier_ratio=self.inliers / max(self.followed, 1),
            ncc=self.ncc,
            in_frame=in_frame,
            source=source,
            reason=reason,
        )


class _Tracker:
    """Holds the renderer, the feature models and the per-object geometry for one clip."""

    def __init__(
        self,
        renderer: PoseRenderer,
        options: TrackOptions,
        scan: tuple[list[ScanFrame], list[np.ndarray]] | None = None,
    ) -> None:
        self.renderer = renderer
        self.options = options
        self.scan = scan
        self.camera = renderer.camera
        self.vertices = [self._object_vertices(i) for i in range(len(renderer.names))]
        self.radii = [float(np.linalg.norm(v, axis=1).max()) for v in self.vertices]
        self.static = StaticGeometry(renderer.model)
        self._features: list[FeatureModel] | None = None
        self._sift = cv2.SIFT.create()
        self._matcher = cv2.BFMatcher(cv2.NORM_L2)

    def _object_vertices(self, index: int) -> np.ndarray:
        """Vertices (V, 3) of the object's rendered meshes in its body frame."""
        import mujoco

        model = self.renderer.model
        body = model.body(self.renderer.names[index]).id
        points = []
        for g in range(model.ngeom):
            if model.geom_bodyid[g] != body or model.geom_group[g] > 2:
                continue
            if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH:
                m = model.geom_dataid[g]
                start, count = model.mesh_vertadr[m], model.mesh_vertnum[m]
                local = model.mesh_vert[start : start + count].astype(np.float64)
            else:
                local = (
                    np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], np.float64)
                    * model.geom_rbound[g]
                )
            rot = matrix_from_quat(model.geom_quat[g])
            points.append(local @ rot.T + model.geom_pos[g])
        if not points:
            raise TrackError(f"object {self.renderer.names[index]!r} has no visible geometry to track")
        return np.concatenate(points)

    @property
    def features(self) -> list[FeatureModel]:
        """Per object: SIFT of its textured mesh rendered from `detect_views` directions, plus (where the scene's
        scan frames are at hand) SIFT of the object in the scan's own frames (`scan_feature_models`)."""
        if self._features is None:
            world_from_cam = self.renderer.world_from_cam.copy()
            features = build_feature_models(self.renderer, self.radii, num_views=self.options.detect_views)
            if self.scan is not None:
                frames, world_from_objects = self.scan
                features = merged_feature_models(
                    features, scan_feature_models(self.renderer, frames, world_from_objects)
                )
                log.info("feature models from %d scan frames: %s", len(frames), [len(f.descriptors) for f in features])
            self.renderer.set_camera(world_from_cam)
            self._features = features
        return self._features

    def in_frame(self, index: int, world_from_object: np.ndarray) -> float:
        cam_from_object = np.linalg.inv(self.renderer.world_from_cam) @ world_from_object
        points = self.vertices[index] @ cam_from_object[:3, :3].T + cam_from_object[:3, 3]
        ahead = points[:, 2] > 1e-3
        if not ahead.any():
            return 0.0
        uv = self.camera.project(points[ahead])
        inside = (
            (uv[:, 0] >= 0) & (uv[:, 0] < self.camera.width_px) & (uv[:, 1] >= 0) & (uv[:, 1] < self.camera.height_px)
        )
        return float(inside.sum()) / len(points)

    def judge(
        self, index: int, step: _Step, typical: _Typical | None = None, expected: _Expected | None = None
    ) -> tuple[bool, str, float]:
        """Whether `step` is a pose of object `index` the frame supports (`_accept`), why not, and its in-image
        fraction."""
        if step.pose is None:
            return False, step.reason, 0.0
        fraction = self.in_frame(index, step.pose)
        depth_m = self.static.penetration_m(self.renderer.names[index], step.pose)
        ok, reason = _accept(step, fraction, self.options, typical, penetration_m=depth_m, expected=expected)
        return ok, reason, fraction

    # ---- render-and-compare

    def _follow(
        self,
        index: int,
        view: RenderedView,
        rend_norm: np.ndarray,
        real_norm: np.ndarray,
        pose: np.ndarray,
        search_px: int = 0,
    ) -> _Step:
        """One update of object `index` from one rendering: LK from rendering to frame, then PnP."""
        opts = self.options
        mask = (view.object_id == index).astype(np.uint8)
        if int(mask.sum()) < opts.min_area_px:
            return _Step(pose=None, reason=f"visible area {int(mask.sum())} px")
        inner = cv2.erode(mask, np.ones((7, 7), np.uint8))
        corners = cv2.goodFeaturesToTrack(rend_norm, opts.max_features, 0.01, 4, mask=inner, blockSize=7)
        if corners is None or len(corners) < opts.min_inliers:
            return _Step(pose=None, reason="too few features on the rendering")
        start = np.rint(corners.reshape(-1, 2)).astype(np.float32)
        shift = _template_shift(rend_norm, real_norm, inner, search_px) if search_px > 0 else np.zeros(2)
        window = (opts.lk_window_px, opts.lk_window_px)
        criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 40, 0.01)
        guess = (start + shift.astype(np.float32)).astype(np.float32)

        def flow(
            src: np.ndarray, dst: np.ndarray, points: np.ndarray, initial: np.ndarray
        ) -> tuple[np.ndarray, np.ndarray]:
            found, ok, _ = cv2.calcOpticalFlowPyrLK(
                src, dst, points, initial, None, None, window, opts.lk_levels, criteria, cv2.OPTFLOW_USE_INITIAL_FLOW
            )
            return np.asarray(found), np.asarray(ok)

        # Forward from the rendering to the frame, then back: a feature must return to within a pixel of its start.
        moved, status = flow(rend_norm, real_norm, start, guess)
        back, status_back = flow(real_norm, rend_norm, moved, start.copy())
        good = (status.ravel() == 1) & (status_back.ravel() == 1) & (np.linalg.norm(back - start, axis=1) < 1.0)
        followed = int(good.sum())
        if followed < opts.min_inliers:
            return _Step(pose=None, followed=followed, reason=f"{followed} features followed")
        cols, rows = start[good, 0].astype(int), start[good, 1].astype(int)
        depth = view.depth_m[rows, cols].astype(np.float64)
        points_cam = backproject(self.camera, start[good].astype(np.float64), depth)
        cam_from_world = np.linalg.inv(self.renderer.world_from_cam)
        cam_from_object = cam_from_world @ pose
        object_from_cam = np.linalg.inv(cam_from_object)
        points_obj = points_cam @ object_from_cam[:3, :3].T + object_from_cam[:3, 3]
        image_points = moved[good].astype(np.float64)
        rvec, tvec = _rt_from_pose(cam_from_object)
        ok, rvec, tvec, inliers = cv2.solvePnPRansac(
            points_obj,
            image_points,
            self.camera.cv_matrix,
            None,
            rvec,
            tvec,
            useExtrinsicGuess=True,
            iterationsCount=200,
            reprojectionError=2.0,
            confidence=0.999,
            flags=cv2.SOLVEPNP_ITERATIVE,
        )
        if not ok or inliers is None or len(inliers) < opts.min_inliers:
            count = 0 if inliers is None else len(inliers)
            return _Step(pose=None, followed=followed, inliers=count, reason=f"{count} PnP inliers")
        keep = inliers.ravel()
        rvec, tvec = cv2.solvePnPRefineLM(points_obj[keep], image_points[keep], self.camera.cv_matrix, None, rvec, tvec)
        # Appearance check on the rendering that produced this update (the pose moved by at most one update).
        ncc = _zncc(rend_norm[inner > 0], real_norm[inner > 0])
        new_pose = self.renderer.world_from_cam @ _pose_from_rt(rvec, tvec)
        return _Step(pose=new_pose, inliers=len(keep), followed=followed, ncc=ncc)

    def refine(self, poses: list[np.ndarray | None], active: list[int], real_norm: np.ndarray) -> dict[int, _Step]:
        """Render-and-compare iterations for the `active` objects (the others are rendered where `poses` says)."""
        current = list(poses)
        steps: dict[int, _Step] = {}
        pending = [i for i in active if current[i] is not None]
        for iteration in range(self.options.max_iterations):
            if not pending:
                break
            search_px = self.options.search_px if iteration == 0 else 0
            view = self.renderer.render(current)
            rend_norm = normalise(cv2.cvtColor(view.rgb, cv2.COLOR_RGB2GRAY))
            still = []
            for i in pending:
                pose = current[i]
                assert pose is not None
                step = self._follow(i, view, rend_norm, real_norm, pose, search_px)
                steps[i] = step
                if step.pose is None:
                    current[i] = None
                    continue
                moved_m = float(np.linalg.norm(step.pose[:3, 3] - pose[:3, 3]))
                turned = rotation_angle_deg(step.pose[:3, :3], pose[:3, :3])
                current[i] = step.pose
                if moved_m > self.options.converge_m or turned > self.options.converge_deg:
                    still.append(i)
            pending = still
        return steps

    # ---- detection

    def detect(
        self, index: int, frame_features: tuple[np.ndarray, np.ndarray], max_hypotheses: int = 4
    ) -> list[np.ndarray]:
        """Candidate poses of object `index` from SIFT matches against its feature model.

        Textures repeat (a printed box shows the same print on several faces), so one RANSAC consensus can be
        the wrong face: PnP + RANSAC is run up to `max_hypotheses` times, each time without the previous
        inliers, and the caller verifies each candidate by render-and-compare.
        """
        pixels, descriptors = frame_features
        model = self.features[index]
        if len(descriptors) < 2 or len(model.descriptors) < 2:
            return []
        pairs = self._matcher.knnMatch(model.descriptors, descriptors, k=2)
        query, train = [], []
        for pair in pairs:
            if len(pair) == 2 and pair[0].distance < 0.8 * pair[1].distance:
                query.append(pair[0].queryIdx)
                train.append(pair[0].trainIdx)
        object_points = model.points_object_m[query]
        image_points = pixels[train]
        candidates = []
        remaining = np.arange(len(query))
        for _ in range(max_hypotheses):
            if len(remaining) < self.options.detect_min_inliers:
                break
            try:
                ok, rvec, tvec, inliers = cv2.solvePnPRansac(
                    object_points[remaining],
                    image_points[remaining],
                    self.camera.cv_matrix,
                    None,
                    iterationsCount=2000,
                    reprojectionError=3.0,
                    confidence=0.9999,
                    flags=cv2.SOLVEPNP_EPNP,
                )
            except cv2.error:  # degenerate minimal sets (all points nearly coincident)
                break
            if not ok or inliers is None or len(inliers) < self.options.detect_min_inliers:
                break
            keep = remaining[inliers.ravel()]
            rvec, tvec = cv2.solvePnPRefineLM(
                object_points[keep], image_points[keep], self.camera.cv_matrix, None, rvec, tvec
            )
            if float(tvec[2, 0]) > 0:
                candidates.append(self.renderer.world_from_cam @ _pose_from_rt(rvec, tvec))
            remaining = np.setdiff1d(remaining, keep)
        return candidates

    def frame_features(self, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """SIFT of the frame upsampled 2x (objects are small in a tabletop clip), in frame pixels."""
        big = cv2.resize(gray, None, fx=2.0, fy=2.0, interpolation=cv2.INTER_LINEAR)
        keypoints, descriptors = self._sift.detectAndCompute(big, None)
        if descriptors is None:
            return np.zeros((0, 2)), np.zeros((0, 128), np.float32)
        # Pixel centres: upsampled pixel u covers frame pixels (u - 0.5) / 2 .. (u + 0.5) / 2.
        return (np.array([kp.pt for kp in keypoints], np.float64) - 0.5) / 2.0, descriptors


def _predict(history: list[np.ndarray | None]) -> np.ndarray | None:
    """Constant-velocity prediction from the last two poses (constant pose from one; None without the last)."""
    last = history[-1] if history else None
    if last is None:
        return None
    before = history[-2] if len(history) >= 2 else None
    if before is None:
        return last.copy()
    pred = np.eye(4)
    pred[:3, 3] = 2 * last[:3, 3] - before[:3, 3]
    delta = last[:3, :3] @ before[:3, :3].T  # world-frame rotation over one frame
    rot = delta @ last[:3, :3]
    u, _, vt = np.linalg.svd(rot)
    pred[:3, :3] = u @ vt
    return pred


@dataclass(frozen=True, kw_only=True)
class _Expected:
    """Where an object's own motion puts it in a frame: the constant-velocity prediction and how far off it a pose
    may lie (`TrackOptions.max_jump_m`, `max_jump_at_rest_m`)."""

    pose: np.ndarray
    max_jump_m: float


def _expected(history: list[np.ndarray | None], dt_s: float, options: TrackOptions) -> _Expected | None:
    """The prediction from the last two poses of `history` (oldest first) and its allowed deviation; None without
    the last pose. With one pose the velocity is unknown, and only `max_jump_m` bounds the deviation."""
    prediction = _predict(history)
    if prediction is None:
        return None
    last, before = history[-1], history[-2] if len(history) >= 2 else None
    if last is None or before is None:
        return _Expected(pose=prediction, max_jump_m=options.max_jump_m)
    step_m = float(np.linalg.norm(last[:3, 3] - before[:3, 3]))
    allowed = options.max_jump_at_rest_m + 2.0 * step_m + GRAVITY_M_S2 * dt_s**2
    return _Expected(pose=prediction, max_jump_m=min(options.max_jump_m, allowed))


@dataclass
class _Typical:
    """An object's recent accepted inlier counts and NCCs: a partly hidden object falls well below its own typical
    values (absolute thresholds cannot tell: a rough grounded mesh matches its frames at NCC 0.5, a perfect one at
    0.98)."""

    inliers: list[int] = field(default_factory=list)
    ncc: list[float] = field(default_factory=list)

    def add(self, step: _Step, keep: int = 15) -> None:
        self.inliers = [*self.inliers, step.inliers][-keep:]
        self.ncc = [*self.ncc, step.ncc][-keep:]


def _accept(
    step: _Step,
    in_frame: float,
    options: TrackOptions,
    typical: _Typical | None = None,
    *,
    penetration_m: float = 0.0,
    expected: _Expected | None = None,
) -> tuple[bool, str]:
    """Whether a refined pose is supported: enough agreeing features, the rendering like the frame, in the image, out
    of the table (`penetration_m`: depth inside the static geometry) and, where the object was tracked in the frame
    before (`expected`), near where its motion puts it."""
    if step.pose is None:
        return False, step.reason
    ratio = step.inliers / max(step.followed, 1)
    min_inliers, min_ncc = float(options.min_inliers), options.min_ncc
    if typical is not None and len(typical.ncc) >= 3:
        min_inliers = max(min_inliers, options.relative_inliers * float(np.median(typical.inliers)))
        min_ncc = max(min_ncc, options.relative_ncc * float(np.median(typical.ncc)))
    if step.inliers < min_inliers or ratio < options.min_inlier_ratio:
        return False, f"{step.inliers} of {step.followed} features agree (need {min_inliers:.0f})"
    if not step.ncc >= min_ncc:
        return False, f"appearance NCC {step.ncc:.2f} (need {min_ncc:.2f})"
    if in_frame < options.min_in_frame:
        return False, f"{in_frame:.0%} in the image"
    if penetration_m > options.max_penetration_m:
        return False, f"{1e3 * penetration_m:.0f} mm inside the table or other static geometry"
    if expected is not None:
        jump_m = float(np.linalg.norm(step.pose[:3, 3] - expected.pose[:3, 3]))
        if jump_m > expected.max_jump_m:
            allowed_mm = 1e3 * expected.max_jump_m
            return False, f"{1e3 * jump_m:.0f} mm off the prediction (its motion allows {allowed_mm:.0f})"
    return True, ""


def track_frames(
    frames_bgr: list[np.ndarray],
    fps: float,
    renderer: PoseRenderer,
    world_from_cam: np.ndarray,
    options: TrackOptions,
    *,
    scan: tuple[list[ScanFrame], list[np.ndarray]] | None = None,
    progress: ProgressFn | None = None,
) -> tuple[np.ndarray, np.ndarray, list[list[FrameScore]]]:
    """Tracks every object through undistorted frames; returns poses (F, N, 4, 4) (NaN where lost), valid (F, N)
    and scores. `scan`: the scan's frames and the objects' poses in them, for the feature models (`load_scan`)."""
    report = progress or no_progress
    tracker = _Tracker(renderer, options, scan)
    count, num = len(frames_bgr), len(renderer.names)
    poses = np.full((count, num, 4, 4), np.nan)
    valid = np.zeros((count, num), bool)
    scores: list[list[FrameScore]] = []
    history: list[list[np.ndarray | None]] = [[] for _ in range(num)]
    typical = [_Typical() for _ in range(num)]
    for f, frame in enumerate(frames_bgr):
        report("tracking", f, count)
        row: list[FrameScore] = [FrameScore() for _ in range(num)]
        if not np.isfinite(world_from_cam[f]).all():
            row = [FrameScore(reason="camera pose unknown") for _ in range(num)]
            for i in range(num):
                history[i].append(None)
            scores.append(row)
            continue
        renderer.set_camera(world_from_cam[f])
        gray = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
        real_norm = normalise(gray)
        expected = [_expected(h, 1.0 / fps, options) for h in history]
        predicted = [None if e is None else e.pose for e in expected]
        steps = tracker.refine(predicted, [i for i in range(num) if predicted[i] is not None], real_norm)
        accepted: list[np.ndarray | None] = [None] * num
        for i, step in steps.items():
            ok, reason, fraction = tracker.judge(i, step, typical[i], expected[i])
            if ok:
                accepted[i] = step.pose
                typical[i].add(step)
                row[i] = step.score(fraction, source="track")
            else:
                row[i] = step.score(fraction, reason=reason)
        missing = [i for i in range(num) if accepted[i] is None]
        if missing:
            features = tracker.frame_features(gray)
            for i in missing:
                best: tuple[_Step, float] | None = None
                failure, failure_ncc = "", -np.inf  # why the best-matching rejected candidate was rejected
                for found in tracker.detect(i, features):
                    # Refine each candidate with the accepted objects in place (they may occlude it).
                    others = [accepted[j] if j != i else found for j in range(num)]
                    step = tracker.refine(others, [i], real_norm).get(i, _Step(pose=None, reason="no refinement"))
                    # Where the object was tracked in the frame before (its step failed), its motion bounds the
                    # detection as it bounds a step: else a pose the jump gate refused would come back here.
                    ok, reason, fraction = tracker.judge(i, step, typical[i], expected[i])
                    if not ok:
                        ncc = step.ncc if np.isfinite(step.ncc) else -np.inf
                        if not failure or ncc > failure_ncc:
                            failure, failure_ncc = reason, ncc
                    elif best is None or step.ncc > best[0].ncc:
                        best = (step, fraction)
                if best is None:
                    detected = f"detected, but {failure}" if failure else "not detected"
                    refused = row[i].reason  # the tracked step's, where there was one
                    row[i] = FrameScore(reason=f"{refused}; {detected}" if refused and failure else refused or detected)
                    continue
                step, fraction = best
                accepted[i] = step.pose
                typical[i].add(step)
                row[i] = step.score(fraction, source="detect")
        for i in range(num):
            pose = accepted[i]
            history[i].append(pose)
            if pose is not None:
                poses[f, i] = pose
                valid[f, i] = True
        scores.append(row)
    report("tracking", count, count)
    _track_backwards(tracker, frames_bgr, 1.0 / fps, world_from_cam, poses, valid, scores, typical, progress=report)
    _trim_run_edges(poses, valid, scores, options.max_edge_deviation_m)
    return poses, valid, scores


def _trim_run_edges(
    poses: np.ndarray, valid: np.ndarray, scores: list[list[FrameScore]], max_deviation_m: float
) -> None:
    """Drops a tracked run's first / last frame next to a gap when it disagrees with the run's motion. In place.

    The frames next to a gap are the partly hidden ones, where PnP on the visible part can still agree with
    itself and yet be off (28 mm seen on the occluded sample with 20% of the box covered). Such an edge frame must
    lie within `max_deviation_m` of the constant-acceleration extrapolation from its three inner neighbours
    (exact in free flight and in sliding; constant velocity from two when the run is that short); if not, it is
    flagged lost. One frame per edge at most: an impact right at a gap also breaks the extrapolation, and
    cascading would eat a genuine track.
    """
    count, num = valid.shape
    for i in range(num):
        for first, last in list(iter_valid_runs(valid[:, i])):
            length = last - first + 1
            if length < 3:
                continue
            edges = []
            if first > 0:
                edges.append((first, 1))
            if last < count - 1:
                edges.append((last, -1))
            for edge, step in edges:
                p1, p2 = poses[edge + step, i, :3, 3], poses[edge + 2 * step, i, :3, 3]
                guess = 2 * p1 - p2
                if length >= 4:
                    guess = 3 * p1 - 3 * p2 + poses[edge + 3 * step, i, :3, 3]
                deviation = float(np.linalg.norm(poses[edge, i, :3, 3] - guess))
                if deviation <= max_deviation_m:
                    continue
                valid[edge, i] = False
                poses[edge, i] = np.nan
                old = scores[edge][i]
                scores[edge][i] = FrameScore(
                    inliers=old.inliers,
                    inlier_ratio=old.inlier_ratio,
                    ncc=old.ncc,
                    in_frame=old.in_frame,
                    reason=f"{1e3 * deviation:.0f} mm off the motion of its tracked neighbours, next to a gap",
                )


def _track_backwards(
    tracker: _Tracker,
    frames_bgr: list[np.ndarray],
    dt_s: float,
    world_from_cam: np.ndarray,
    poses: np.ndarray,
    valid: np.ndarray,
    scores: list[list[FrameScore]],
    typical: list[_Typical],
    *,
    progress: ProgressFn,
) -> None:
    """Extends every track backwards into the frames before it, where the forward pass had not found the object yet
    (a wrong first detection, or the end of an occlusion seen only once the object is re-detected). In place."""
    count, num = valid.shape
    todo = [f for f in range(count - 2, -1, -1) if (~valid[f] & valid[f + 1]).any()]
    if not todo:
        return
    for f in range(count - 2, -1, -1):
        lost_here = [i for i in range(num) if not valid[f, i] and valid[f + 1, i]]
        if not lost_here or not np.isfinite(world_from_cam[f]).all():
            continue
        progress("tracking backwards", count - 1 - f, count)
        tracker.renderer.set_camera(world_from_cam[f])
        real_norm = normalise(cv2.cvtColor(frames_bgr[f], cv2.COLOR_BGR2GRAY))
        current: list[np.ndarray | None] = [poses[f, j] if valid[f, j] else None for j in range(num)]
        expected: dict[int, _Expected] = {}
        for i in lost_here:
            later = [poses[f + 2, i] if f + 2 < count and valid[f + 2, i] else None, poses[f + 1, i]]
            guess = _expected(later, dt_s, tracker.options)  # the motion run backwards: later frames first
            assert guess is not None
            expected[i] = guess
            current[i] = guess.pose
        steps = tracker.refine(current, lost_here, real_norm)
        for i in lost_here:
            step = steps.get(i, _Step(pose=None, reason="no refinement"))
            ok, _, fraction = tracker.judge(i, step, typical[i], expected[i])
            if ok and step.pose is not None:
                poses[f, i] = step.pose
                valid[f, i] = True
                scores[f][i] = step.score(fraction, source="track_backwards")
