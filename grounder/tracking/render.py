"""Rendering a grounded scene at candidate object poses, for model-based tracking.

One `PoseRenderer` holds a MuJoCo model of the scene plus a camera with the clip's exact pinhole intrinsics, and
renders colour, depth and per-pixel object ids for a set of object poses in one go. Objects that are not being
shown are parked behind the camera.

Pixel conventions: images are row 0 at the top. `cv_matrix` is K for OpenCV pixel coordinates (the centre of the
upper-left pixel is (0, 0)); COLMAP's K (centre of the upper-left pixel at (0.5, 0.5)) has cx, cy 0.5 larger.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType

import cv2
import mujoco
import numpy as np

from grounder.errors import GrounderError
from grounder.sim.rollout import free_joints
from image2sim_common.rotations import quat_from_matrix

os.environ.setdefault("MUJOCO_GL", "osmesa")

_TRACK_CAMERA = "__image2sim_track"
_OPENCV_TO_MUJOCO_CAM = np.diag([1.0, -1.0, -1.0])


@dataclass(frozen=True, kw_only=True)
class PinholeCamera:
    """Pinhole intrinsics of the clip, OpenCV pixel convention (upper-left pixel centre at (0, 0)).

    Attributes:
        width_px, height_px: image size.
        cv_matrix: (3, 3) K.
    """

    width_px: int
    height_px: int
    cv_matrix: np.ndarray

    @classmethod
    def from_colmap(
        cls, width_px: int, height_px: int, fx_px: float, fy_px: float, cx_px: float, cy_px: float
    ) -> PinholeCamera:
        """From intrinsics in COLMAP's convention (upper-left pixel centre at (0.5, 0.5))."""
        matrix = np.array([[fx_px, 0.0, cx_px - 0.5], [0.0, fy_px, cy_px - 0.5], [0.0, 0.0, 1.0]])
        return cls(width_px=int(width_px), height_px=int(height_px), cv_matrix=matrix)

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """(N, 3) camera-frame points (OpenCV axes) -> (N, 2) pixels."""
        uvw = points_cam @ self.cv_matrix.T
        return uvw[:, :2] / uvw[:, 2:3]


@dataclass(frozen=True, kw_only=True)
class RenderedView:
    """One rendering. rgb (H, W, 3) uint8; depth_m (H, W) float32, distance along the optical axis; object_id
    (H, W) int16, index into the renderer's objects or -1 for anything else."""

    rgb: np.ndarray
    depth_m: np.ndarray
    object_id: np.ndarray


def backproject(camera: PinholeCamera, pixels: np.ndarray, depth_m: np.ndarray) -> np.ndarray:
    """(N, 2) OpenCV pixels with depths (N,) -> (N, 3) camera-frame points."""
    k = camera.cv_matrix
    x = (pixels[:, 0] - k[0, 2]) / k[0, 0]
    y = (pixels[:, 1] - k[1, 2]) / k[1, 1]
    return np.stack([x * depth_m, y * depth_m, depth_m], axis=1)


class PoseRenderer:
    """Renders the scene's free bodies at given poses from the clip's camera (a resource: use it as a context manager).

    Args:
        scene_xml: the grounded scene (free joint per object).
        camera: the clip's intrinsics.
        shadows: render shadows (off by default: the scene's lights are not the clip's, and it is 5x faster).
    """

    def __init__(self, scene_xml: Path, camera: PinholeCamera, *, shadows: bool = False) -> None:
        try:
            spec = mujoco.MjSpec.from_file(str(scene_xml))
        except Exception as exc:
            raise GrounderError(
                f"cannot read the scene {scene_xml}: {exc}; pass a scene folder written by ground"
            ) from exc
        spec.visual.global_.offwidth = max(spec.visual.global_.offwidth, camera.width_px)
        spec.visual.global_.offheight = max(spec.visual.global_.offheight, camera.height_px)
        # No multisampling: on the CPU renderer it doubles the time of a rendering (67 against 33 ms at 640 x 480),
        # and it changes only the colour of silhouette edges (depth and object ids come out the same), which the
        # tracker never follows: its features lie inside the eroded silhouette.
        spec.visual.quality.offsamples = 0
        cam = spec.worldbody.add_camera(name=_TRACK_CAMERA)
        k = camera.cv_matrix
        cam.resolution = [camera.width_px, camera.height_px]
        cam.sensor_size = [camera.width_px * 1e-5, camera.height_px * 1e-5]
        cam.focal_pixel = [float(k[0, 0]), float(k[1, 1])]
        # MuJoCo's principal point is an offset from the image centre, positive to the left and up (measured in
        # tests): cx_colmap = W/2 - offset_x. OpenCV's cx is 0.5 smaller than COLMAP's.
        cam.principal_pixel = [camera.width_px / 2 - (k[0, 2] + 0.5), camera.height_px / 2 - (k[1, 2] + 0.5)]
        try:
            self.model = spec.compile()
        except Exception as exc:
            raise GrounderError(f"MuJoCo cannot compile {scene_xml} for tracking: {exc}") from exc
        self.camera = camera
        self.data = mujoco.MjData(self.model)
        self.cam_id = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_CAMERA, _TRACK_CAMERA)
        self.joints = free_joints(self.model)
        if not self.joints:
            raise GrounderError(f"{scene_xml} has no free bodies to track; pass a scene written by ground")
        self.names = tuple(j.body for j in self.joints)
        body_to_object = {int(self.model.body(j.body).id): i for i, j in enumerate(self.joints)}
        self._geom_object = np.full(self.model.ngeom + 1, -1, np.int16)
        for g in range(self.model.ngeom):
            self._geom_object[g] = body_to_object.get(int(self.model.geom_bodyid[g]), -1)
        self._renderer = mujoco.Renderer(self.model, camera.height_px, camera.width_px)
        self._renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = int(shadows)
        self._renderer.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0
        self._shadows = shadows
        self.world_from_cam = np.eye(4)
        self.set_camera(np.eye(4))

    def __enter__(self) -> PoseRenderer:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def close(self) -> None:
        self._renderer.close()

    def set_camera(self, world_from_cam: np.ndarray) -> None:
        """Moves the render camera; `world_from_cam` (4, 4) uses OpenCV axes."""
        self.world_from_cam = np.array(world_from_cam, np.float64)
        self.model.cam_pos[self.cam_id] = self.world_from_cam[:3, 3]
        self.model.cam_quat[self.cam_id] = quat_from_matrix(self.world_from_cam[:3, :3] @ _OPENCV_TO_MUJOCO_CAM)

    def parked_pose(self) -> np.ndarray:
        """A world pose 50 m behind the camera: out of view."""
        pose = np.eye(4)
        pose[:3, 3] = self.world_from_cam[:3, 3] - 50.0 * self.world_from_cam[:3, 2]
        return pose

    def render(self, world_from_objects: list[np.ndarray | None], *, rgb: bool = True) -> RenderedView:
        """Renders with object i at world_from_objects[i] (4, 4), or parked when None."""
        for fj, pose in zip(self.joints, world_from_objects, strict=True):
            pose = self.parked_pose() if pose is None else pose
            self.data.qpos[fj.pos] = pose[:3, 3]
            self.data.qpos[fj.quat] = quat_from_matrix(pose[:3, :3])
        mujoco.mj_kinematics(self.model, self.data)
        mujoco.mj_camlight(self.model, self.data)
        renderer = self._renderer
        renderer.update_scene(self.data, camera=self.cam_id)
        renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = int(self._shadows)
        renderer.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0
        color = renderer.render().copy() if rgb else np.zeros((1, 1, 3), np.uint8)
        renderer.enable_depth_rendering()
        depth = renderer.render().astype(np.float32)
        renderer.disable_depth_rendering()
        return RenderedView(rgb=color, depth_m=depth, object_id=self._object_ids_of_last_render())

    def _object_ids_of_last_render(self) -> np.ndarray:
        """(H, W) int16 object index per pixel (-1: no object) of the depth render just drawn.

        `mujoco.Renderer` draws a depth render with segmentation colours, the same picture its segmentation render
        draws, so the ids are read from that render's colour buffer instead of drawing the scene a third time
        (software rendering is most of the tracker's time: the marker toss test took 80 s instead of 93 s). The colours
        are decoded as `mujoco.Renderer` decodes them: segment id + 1 in 24 bits, rows bottom-up.
        """
        renderer = self._renderer
        colour = np.empty((renderer.height, renderer.width, 3), np.uint8)
        mujoco.mjr_readPixels(colour, None, renderer._rect, renderer._mjr_context)
        segment = colour[::-1].astype(np.int32) @ np.array([1, 1 << 8, 1 << 16], np.int32)
        scene = renderer.scene
        object_of_segment = np.full(scene.ngeom + 1, -1, np.int16)
        for g in scene.geoms[: scene.ngeom]:
            if g.segid != -1 and g.objtype == int(mujoco.mjtObj.mjOBJ_GEOM) and 0 <= g.objid < self.model.ngeom:
                object_of_segment[g.segid + 1] = self._geom_object[g.objid]
        return object_of_segment[np.clip(segment, 0, scene.ngeom)]


@dataclass(frozen=True, kw_only=True)
class FeatureModel:
    """SIFT features of one object, each with its 3D point in the object frame.

    Attributes:
        descriptors: (N, 128) float32.
        points_object_m: (N, 3) float64.
    """

    descriptors: np.ndarray
    points_object_m: np.ndarray


def fibonacci_directions(count: int) -> np.ndarray:
    """(count, 3) unit vectors spread evenly over the sphere."""
    i = np.arange(count) + 0.5
    polar = np.arccos(1 - 2 * i / count)
    azimuth = np.pi * (1 + 5**0.5) * i
    return np.stack([np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar), np.cos(polar)], axis=1)


def _rotation_taking(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """A rotation R with R a = b (unit vectors)."""
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    v = np.cross(a, b)
    c = float(np.dot(a, b))
    if c < -1 + 1e-9:
        axis = np.cross(a, [1.0, 0.0, 0.0])
        if np.linalg.norm(axis) < 1e-6:
            axis = np.cross(a, [0.0, 1.0, 0.0])
        axis /= np.linalg.norm(axis)
        return 2 * np.outer(axis, axis) - np.eye(3)
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1 + c)


def build_feature_models(renderer: PoseRenderer, radii_m: list[float], *, num_views: int = 26) -> list[FeatureModel]:
    """Renders the objects from `num_views` directions and keeps their SIFT features with their 3D points.

    All objects are rendered together, each in its own cell of a grid over the image, at a distance where it
    fills its cell; SIFT runs on each cell's crop.

    Args:
        renderer: the scene renderer (its camera pose is used as is; the objects are placed in front of it).
        radii_m: per object, its bounding radius.
        num_views: view directions, evenly spread over the sphere (tossed objects can show any side).
    """
    sift = cv2.SIFT.create()
    camera = renderer.camera
    count = len(radii_m)
    cols = int(np.ceil(np.sqrt(count * camera.width_px / camera.height_px)))
    rows = int(np.ceil(count / cols))
    cell_w, cell_h = camera.width_px / cols, camera.height_px / rows
    cells = []
    for index, radius in enumerate(radii_m):
        row, col = divmod(index, cols)
        centre_px = np.array([(col + 0.5) * cell_w, (row + 0.5) * cell_h])
        distance = radius * camera.cv_matrix[1, 1] / (0.42 * min(cell_w, cell_h))
        ray = np.linalg.solve(camera.cv_matrix, np.array([*centre_px, 1.0]))
        cells.append((centre_px, ray / ray[2] * distance))
    descriptors: list[list[np.ndarray]] = [[] for _ in range(count)]
    points: list[list[np.ndarray]] = [[] for _ in range(count)]
    for direction in fibonacci_directions(num_views):
        cam_from_objects = []
        for _, position_cam in cells:
            cam_from_object = np.eye(4)
            # The object's `direction` (object frame) points at the camera.
            to_camera = -position_cam / np.linalg.norm(position_cam)
            cam_from_object[:3, :3] = _rotation_taking(direction, to_camera)
            cam_from_object[:3, 3] = position_cam
            cam_from_objects.append(cam_from_object)
        view = renderer.render([renderer.world_from_cam @ p for p in cam_from_objects])
        gray = cv2.cvtColor(view.rgb, cv2.COLOR_RGB2GRAY)
        for index, cam_from_object in enumerate(cam_from_objects):
            mask = (view.object_id == index).astype(np.uint8)
            ys, xs = np.nonzero(mask)
            if len(xs) < 50:
                continue
            y0, y1 = max(0, ys.min() - 8), min(camera.height_px, ys.max() + 9)
            x0, x1 = max(0, xs.min() - 8), min(camera.width_px, xs.max() + 9)
            inner = cv2.erode(mask, np.ones((3, 3), np.uint8))[y0:y1, x0:x1]
            keypoints, desc = sift.detectAndCompute(gray[y0:y1, x0:x1], inner)
            if desc is None or not keypoints:
                continue
            pixels = np.array([kp.pt for kp in keypoints], np.float64) + np.array([x0, y0], np.float64)
            rr = np.clip(np.rint(pixels[:, 1]).astype(int), 0, camera.height_px - 1)
            cc = np.clip(np.rint(pixels[:, 0]).astype(int), 0, camera.width_px - 1)
            depth = view.depth_m[rr, cc].astype(np.float64)
            keep = (view.object_id[rr, cc] == index) & (depth > 0)
            points_cam = backproject(camera, pixels[keep], depth[keep])
            object_from_cam = np.linalg.inv(cam_from_object)
            points[index].append(points_cam @ object_from_cam[:3, :3].T + object_from_cam[:3, 3])
            descriptors[index].append(desc[keep])
    models = []
    for index in range(count):
        if not descriptors[index]:
            raise GrounderError(
                f"object {renderer.names[index]!r} shows no texture features when rendered; is its texture missing?"
            )
        models.append(
            FeatureModel(
                descriptors=np.concatenate(descriptors[index]).astype(np.float32),
                points_object_m=np.concatenate(points[index]),
            )
        )
    return models


@dataclass(frozen=True, kw_only=True)
class ScanFrame:
    """One scan frame for the feature models: its undistorted gray image (the clip's camera and size) and pose."""

    gray: np.ndarray
    world_from_cam: np.ndarray


def scan_feature_models(
    renderer: PoseRenderer, frames: list[ScanFrame], world_from_objects: list[np.ndarray]
) -> list[FeatureModel]:
    """SIFT features of each object in the scan's own frames, each with its 3D point in the object frame.

    The objects stood still at `world_from_objects` during the scan, whose frames have known cameras: rendering the
    grounded scene from each frame's camera gives every pixel's object and depth, so a SIFT feature of the real frame
    inside an object's (eroded) silhouette gets its 3D point. Real frames carry the texture as the camera saw it,
    which a render of the baked texture loses: on `samples/toss_markers` frames 0-5, 107-130 of the bowl's matches
    were right (within 3 px of the truth) against 15-18 from the rendered model, and the bowl was found in the first
    frame instead of the sixth. Frames are upsampled 2x, as the clip's are (`_Tracker.frame_features`).
    """
    sift = cv2.SIFT.create()
    camera = renderer.camera
    count = len(renderer.names)
    descriptors: list[list[np.ndarray]] = [[] for _ in range(count)]
    points: list[list[np.ndarray]] = [[] for _ in range(count)]
    kernel = np.ones((7, 7), np.uint8)
    for frame in frames:
        renderer.set_camera(frame.world_from_cam)
        view = renderer.render(list(world_from_objects), rgb=False)
        big = cv2.resize(frame.gray, None, fx=2.0, fy=2.0, interpolation=cv2.INTER_LINEAR)
        for index in range(count):
            inner = cv2.erode((view.object_id == index).astype(np.uint8), kernel)
            if int(inner.sum()) < 200:
                continue
            mask = cv2.resize(inner, None, fx=2.0, fy=2.0, interpolation=cv2.INTER_NEAREST)
            keypoints, desc = sift.detectAndCompute(big, mask)
            if desc is None or not keypoints:
                continue
            pixels = (np.array([kp.pt for kp in keypoints], np.float64) - 0.5) / 2.0
            rr = np.clip(np.rint(pixels[:, 1]).astype(int), 0, camera.height_px - 1)
            cc = np.clip(np.rint(pixels[:, 0]).astype(int), 0, camera.width_px - 1)
            depth = view.depth_m[rr, cc].astype(np.float64)
            keep = (view.object_id[rr, cc] == index) & (depth > 0)
            points_world = backproject(camera, pixels[keep], depth[keep]) @ frame.world_from_cam[:3, :3].T
            points_world += frame.world_from_cam[:3, 3]
            object_from_world = np.linalg.inv(world_from_objects[index])
            points[index].append(points_world @ object_from_world[:3, :3].T + object_from_world[:3, 3])
            descriptors[index].append(desc[keep])
    return [
        FeatureModel(
            descriptors=np.concatenate(descriptors[i]).astype(np.float32)
            if descriptors[i]
            else np.zeros((0, 128), np.float32),
            points_object_m=np.concatenate(points[i]) if points[i] else np.zeros((0, 3)),
        )
        for i in range(count)
    ]


def merged_feature_models(first: list[FeatureModel], second: list[FeatureModel]) -> list[FeatureModel]:
    """Per object, the features of both models."""
    return [
        FeatureModel(
            descriptors=np.concatenate([a.descriptors, b.descriptors]).astype(np.float32),
            points_object_m=np.concatenate([a.points_object_m, b.points_object_m]),
        )
        for a, b in zip(first, second, strict=True)
    ]
